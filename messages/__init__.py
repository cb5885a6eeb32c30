"""Everything on the wire and its storage: typed message schemas (schemas.py), their JSON encoding (codec.py), the
key layout (keys.py), the Zenoh transport (transport/) and MCAP recordings (recording/).

Only the pure part is imported here, so that the market's rules and the agent's model, which read messages, never
load the Zenoh binding: a process that talks imports ``messages.transport`` itself.

This package imports only ``scenarios`` (for the day's hours and the naming rule), never ``dmo`` or
``microgrid_agent``: both sides of the market build on it.
"""

from .codec import MAX_PAYLOAD_BYTES, MessageError, decode, encode, make_receipt, make_rejection, sha256
from .keys import (Keys, ParsedKey, check_agent_id, check_route, check_run_id, key_pattern, new_run_id, parse_key,
                   relative_key, sender_matches_key)
from .schemas import (DMO, HOURS, KINDS, MODELS, PHASES, REJECT_CODES, SCHEMA_VERSION, SCHEMAS, AgentTotals, Award,
                      Bid, BidStep, CallForBids, Clock, DaySummary, Envelope, GridState, Incident, Message,
                      MeterReport, Receipt, Registration, Rejection, Schedule, SettlementStatement, StatementLine,
                      json_schema)

__all__ = [
    "MAX_PAYLOAD_BYTES", "MessageError", "decode", "encode", "make_receipt", "make_rejection", "sha256",
    "Keys", "ParsedKey", "check_agent_id", "check_route", "check_run_id", "key_pattern", "new_run_id", "parse_key",
    "relative_key", "sender_matches_key",
    "DMO", "HOURS", "KINDS", "MODELS", "PHASES", "REJECT_CODES", "SCHEMA_VERSION", "SCHEMAS", "AgentTotals", "Award",
    "Bid", "BidStep", "CallForBids", "Clock", "DaySummary", "Envelope", "GridState", "Incident", "Message",
    "MeterReport", "Receipt", "Registration", "Rejection", "Schedule", "SettlementStatement", "StatementLine", "json_schema",
]
