"""Everything on the wire: typed message schemas, their JSON encoding, key expressions and the Zenoh transport."""

from .codec import MAX_PAYLOAD_BYTES, MessageError, decode, encode, make_rejection
from .keys import (ParsedKey, Keys, check_agent_id, check_route, check_run_id, new_run_id, parse_key,
                   sender_matches_key)
from .schemas import (DMO, HOURS, KINDS, MODELS, PHASES, REJECT_CODES, SCHEMA_VERSION, SCHEMAS, AgentTotals, Award,
                      Bid, BidStep, CallForBids, Clock, DaySummary, Envelope, GridState, Incident, Message,
                      MeterReport, Registration, Rejection, Schedule, SettlementStatement, StatementLine,
                      json_schema)
from .transport import Bus, BusConfig, Subscription, add_bus_arguments, bus_config_from_args

__all__ = [
    "MAX_PAYLOAD_BYTES", "MessageError", "decode", "encode", "make_rejection",
    "ParsedKey", "Keys", "check_agent_id", "check_route", "check_run_id", "new_run_id", "parse_key",
    "sender_matches_key",
    "DMO", "HOURS", "KINDS", "MODELS", "PHASES", "REJECT_CODES", "SCHEMA_VERSION", "SCHEMAS", "AgentTotals", "Award",
    "Bid", "BidStep", "CallForBids", "Clock", "DaySummary", "Envelope", "GridState", "Incident", "Message",
    "MeterReport", "Registration", "Rejection", "Schedule", "SettlementStatement", "StatementLine", "json_schema",
    "Bus", "BusConfig", "Subscription", "add_bus_arguments", "bus_config_from_args",
]
