"""Typed, versioned schemas of every message on the wire, one frozen pydantic model per kind, and their JSON Schemas.

Conventions: powers in MW (``_mw``), energies in MWh (``_mwh``), prices in $/MWh (``_per_mwh``), money in $,
durations in seconds (``_s``), timestamps in ns since the Unix epoch. Hours are numbered 1..24. A positive
transfer is an import into the microgrid, a negative one an export (the paper's P_M and P_sch).

Scalars are strict (no "1" for 1, no 0 for false) and floats finite, so a message means one thing only. Build
messages from Python scalars: ``ndarray.tolist()`` rather than numpy integers or booleans.
"""

from __future__ import annotations

import datetime as _dt
import math
from typing import Annotated, Any, Literal, Union, get_args

from pydantic import (AfterValidator, BaseModel, ConfigDict, Field, Strict, TypeAdapter, ValidationInfo,
                      model_validator)

from scenarios.horizon import HOURS
from scenarios.names import DMO, NAME_PATTERN, RESERVED_NAMES

SCHEMA_VERSION = 1
MAX_SUBPERIODS = 60
MAX_BID_STEPS = 16
MAX_UNITS = 64
MAX_AGENTS = 1024
CENT = 0.01

# Strict scalars: the wire never coerces between types.
Float = Annotated[float, Strict()]
NonNeg = Annotated[float, Strict(), Field(ge=0)]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Text = Annotated[str, Strict(), Field(max_length=500)]
Name = Annotated[str, Strict(), Field(pattern=NAME_PATTERN)]


def _not_reserved(name: str) -> str:
    if name.lower() in RESERVED_NAMES:
        raise ValueError(f"{name!r} is a reserved name, not an agent id")
    return name


AgentId = Annotated[str, Strict(), Field(pattern=NAME_PATTERN), AfterValidator(_not_reserved)]
Hour = Annotated[int, Strict(), Field(ge=1, le=HOURS)]
Subperiods = Annotated[int, Strict(), Field(ge=1, le=MAX_SUBPERIODS)]
Count = Annotated[int, Strict(), Field(ge=0, le=2**63 - 1)]
Timestamp = Annotated[int, Strict(), Field(ge=0, le=2**63 - 1)]
Phase = Literal["registration", "bidding", "clearing", "scheduling", "realtime", "settlement"]
PHASES: tuple[str, ...] = get_args(Phase)
# Why a payload was refused: codec.decode and keys.check_route give the first eight, the DMO the rest.
RejectCode = Literal["oversize", "not_json", "not_object", "unknown_kind", "unsupported_version", "invalid",
                     "wrong_key", "unauthorised", "late", "duplicate", "wrong_day", "unregistered"]
REJECT_CODES: tuple[str, ...] = get_args(RejectCode)
Hourly = Annotated[tuple[Float, ...], Field(min_length=HOURS, max_length=HOURS)]
MarketDay = Annotated[str, Strict(), Field(pattern=r"^[0-9]{4}-[0-9]{2}-[0-9]{2}$")]


class _WireModel(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False,
                              json_schema_serialization_defaults_required=True)


def _check_length(values: tuple, subperiods: int, field: str) -> None:
    if len(values) != subperiods:
        raise ValueError(f"{field} has {len(values)} values, expected subperiods={subperiods}")


class Envelope(_WireModel):
    """Fields every message carries. ``seq`` and ``sent_at`` are stamped by the transport when published."""

    kind: str  # each message type narrows it to its literal tag; declared here so it comes first on the wire
    schema_version: Annotated[int, Strict(), Field(ge=1, le=SCHEMA_VERSION)] = SCHEMA_VERSION
    sender: Name
    market_day: MarketDay
    seq: Count = 0
    sent_at: Timestamp = 0

    @model_validator(mode="before")
    @classmethod
    def _every_field_on_the_wire(cls, data: Any, info: ValidationInfo) -> Any:
        # Defaults exist for building messages in Python; a received message states every field, so
        # a reader never has to guess what the sender's defaults were. Only messages have defaults: the
        # nested models (steps, lines, totals, incidents) have none, so pydantic already requires theirs.
        if info.mode == "json" and isinstance(data, dict):
            missing = [name for name in cls.model_fields if name not in data]
            if missing:
                raise ValueError(f"missing field {missing[0]!r}")
        return data

    @model_validator(mode="after")
    def _real_day(self):
        try:
            _dt.date.fromisoformat(self.market_day)
        except ValueError:
            raise ValueError(f"market_day {self.market_day!r} is not a calendar date") from None
        return self


class _FromAgent(Envelope):
    """A message an agent sends about itself: the agent is the sender."""

    @property
    def agent(self) -> str:
        return self.sender

    @model_validator(mode="after")
    def _sent_by_an_agent(self):
        _not_reserved(self.sender)
        return self


class _FromDmo(Envelope):
    @model_validator(mode="after")
    def _sent_by_dmo(self):
        if self.sender != DMO:
            raise ValueError(f"sender must be {DMO!r}, not {self.sender!r}")
        return self


# --- registration -------------------------------------------------------------------------------------------

class Registration(_FromAgent):
    """Phase 1, agent -> DMO: the agent announces itself and what it can exchange with the grid."""

    kind: Literal["registration"] = "registration"
    case: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    max_import_mw: NonNeg
    max_export_mw: NonNeg


# --- bidding ------------------------------------------------------------------------------------------------

class CallForBids(_FromDmo):
    """Phase 2, DMO -> all agents: the day's market terms; bids are due ``deadline_s`` after ``sent_at``."""

    kind: Literal["call_for_bids"] = "call_for_bids"
    iso_price_per_mwh: Hourly
    price_floor_per_mwh: Float
    price_cap_per_mwh: Float
    import_limit_mw: NonNeg
    export_limit_mw: NonNeg
    penalty_per_mwh: NonNeg
    credit_per_mwh: NonNeg = 0.0
    subperiods: Subperiods
    deadline_s: Annotated[float, Strict(), Field(gt=0, le=86_400)]

    @model_validator(mode="after")
    def _price_band(self):
        if self.price_floor_per_mwh > self.price_cap_per_mwh:
            raise ValueError(f"price_floor_per_mwh {self.price_floor_per_mwh} exceeds price_cap_per_mwh "
                             f"{self.price_cap_per_mwh}")
        return self


class BidStep(_WireModel):
    """One price-quantity step: buy up to ``quantity_mw`` at up to ``price_per_mwh``; negative = sell at least at it."""

    price_per_mwh: Float
    quantity_mw: Float


class Bid(_FromAgent):
    """Phase 2, agent -> DMO: per hour 1..24, up to MAX_BID_STEPS steps (no steps = no offer that hour)."""

    kind: Literal["bid"] = "bid"
    hours: Annotated[tuple[Annotated[tuple[BidStep, ...], Field(max_length=MAX_BID_STEPS)], ...],
                     Field(min_length=HOURS, max_length=HOURS)]


# --- clearing -----------------------------------------------------------------------------------------------

class Award(_FromDmo):
    """Phase 3, DMO -> one agent: its hourly award P_sch, the clearing prices and the settlement terms."""

    kind: Literal["award"] = "award"
    agent: AgentId
    p_sch_mw: Hourly
    clearing_price_per_mwh: Hourly
    penalty_per_mwh: NonNeg
    credit_per_mwh: NonNeg = 0.0
    subperiods: Subperiods
    rules_version: Annotated[int, Strict(), Field(ge=1, le=10_000)]
    rules: Annotated[str, Strict(), Field(max_length=4000)]


# --- scheduling ---------------------------------------------------------------------------------------------

class Schedule(_FromAgent):
    """Phase 4, agent -> DMO: the day-ahead schedule the agent solved against its award."""

    kind: Literal["schedule"] = "schedule"
    status: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    commitment: Annotated[dict[Annotated[str, Strict(), Field(pattern=NAME_PATTERN)],
                               Annotated[tuple[Literal[0, 1], ...], Field(min_length=HOURS, max_length=HOURS)]],
                          Field(max_length=MAX_UNITS)]
    expected_cost: Float
    p_m_expected_mw: Hourly
    scenarios: Annotated[int, Strict(), Field(ge=1, le=100_000)]
    mip_gap: Annotated[float, Strict(), Field(ge=0)] | None = None


# --- real-time operation ------------------------------------------------------------------------------------

class Clock(_FromDmo):
    """DMO -> all: the simulated clock; a new phase (and, in real time, a new hour) starts now."""

    kind: Literal["clock"] = "clock"
    phase: Phase
    hour: Hour | None = None
    deadline_s: Annotated[float, Strict(), Field(gt=0, le=86_400)]

    @model_validator(mode="after")
    def _hour_in_realtime(self):
        if (self.phase == "realtime") != (self.hour is not None):
            raise ValueError("hour is required in phase realtime and only there")
        return self


class GridState(_FromDmo):
    """Phase 5, DMO -> all, once per hour: the grid's realised state; connected False = islanded (U = 0)."""

    kind: Literal["grid_state"] = "grid_state"
    hour: Hour
    subperiods: Subperiods
    connected: tuple[Bool, ...]

    @model_validator(mode="after")
    def _lengths(self):
        _check_length(self.connected, self.subperiods, "connected")
        return self


class MeterReport(_FromAgent):
    """Phase 5, agent -> DMO, once per hour: metered transfer P_M per sub-period and its deviation P_M - P_sch."""

    kind: Literal["meter_report"] = "meter_report"
    hour: Hour
    subperiods: Subperiods
    p_m_mw: tuple[Float, ...]
    deviation_mw: tuple[Float, ...]

    @model_validator(mode="after")
    def _lengths(self):
        _check_length(self.p_m_mw, self.subperiods, "p_m_mw")
        _check_length(self.deviation_mw, self.subperiods, "deviation_mw")
        return self


# --- settlement ---------------------------------------------------------------------------------------------

class StatementLine(_WireModel):
    """One hour of a statement. ``import_mwh`` is the settled import (metered sub-periods as reported, missing ones
    by the missing-report rule); ``deviation_mwh`` the sum of max(P_M - P_sch, 0) dt, ``under_import_mwh`` the sum
    of max(P_sch - P_M, 0) dt; total = energy_charge + deviation_penalty - deviation_credit."""

    hour: Hour
    p_sch_mw: Float
    clearing_price_per_mwh: Float
    energy_charge: Float
    import_mwh: Float
    deviation_mwh: NonNeg
    under_import_mwh: NonNeg
    deviation_penalty: NonNeg
    deviation_credit: NonNeg
    total: Float
    missing: Bool
    missing_subperiods: Annotated[int, Strict(), Field(ge=0, le=MAX_SUBPERIODS)]

    @model_validator(mode="after")
    def _adds_up(self):
        _check_sum(self.total, self.energy_charge + self.deviation_penalty - self.deviation_credit, "total")
        return self


class SettlementStatement(_FromDmo):
    """Phase 6, DMO -> one agent: its itemised bill, 24 lines and their totals (each the sum of its lines)."""

    kind: Literal["settlement_statement"] = "settlement_statement"
    agent: AgentId
    penalty_per_mwh: NonNeg
    credit_per_mwh: NonNeg
    rules_version: Annotated[int, Strict(), Field(ge=1, le=10_000)]
    lines: Annotated[tuple[StatementLine, ...], Field(min_length=HOURS, max_length=HOURS)]
    energy_charge: Float
    deviation_penalty: NonNeg
    deviation_credit: NonNeg
    total: Float
    missing_subperiods: Count

    @model_validator(mode="after")
    def _adds_up(self):
        hours = [line.hour for line in self.lines]
        if hours != list(range(1, HOURS + 1)):
            raise ValueError("lines must be hours 1..24 in order")
        for name in ("energy_charge", "deviation_penalty", "deviation_credit", "total"):
            _check_sum(getattr(self, name), math.fsum(getattr(line, name) for line in self.lines), name)
        if self.missing_subperiods != sum(line.missing_subperiods for line in self.lines):
            raise ValueError("missing_subperiods is not the sum of the lines'")
        return self


def _check_sum(stated: float, computed: float, name: str) -> None:
    # Statements are reproducible to the cent, so totals must add up to the cent.
    if abs(stated - computed) > CENT + 1e-9 * abs(computed):
        raise ValueError(f"{name} {stated} does not add up (lines give {computed:.2f})")


class AgentTotals(_WireModel):
    energy_charge: Float
    deviation_penalty: NonNeg
    deviation_credit: NonNeg
    total: Float


class Incident(_WireModel):
    """Something that went wrong during the day: a late, missing or vanished agent, a rejected message."""

    agent: AgentId | None
    phase: Phase
    hour: Hour | None
    reason: Text


class DaySummary(_FromDmo):
    """Phase 6, DMO -> all: the day's outcome, once every statement is out."""

    kind: Literal["day_summary"] = "day_summary"
    agents: Annotated[tuple[AgentId, ...], Field(max_length=MAX_AGENTS)]
    clearing_price_per_mwh: Hourly
    totals: Annotated[dict[Annotated[str, Strict(), Field(pattern=NAME_PATTERN)], AgentTotals],
                      Field(max_length=MAX_AGENTS)]
    rejected_messages: Count
    incidents: Annotated[tuple[Incident, ...], Field(max_length=10_000)]

    @model_validator(mode="after")
    def _known_agents(self):
        unknown = sorted(set(self.totals) - set(self.agents))
        if unknown:
            raise ValueError(f"totals name agents not in agents: {', '.join(unknown)}")
        return self


class Rejection(_FromDmo):
    """DMO -> recorder: a received payload was refused; says which, where and why, so the recording keeps it."""

    kind: Literal["rejection"] = "rejection"
    key: Annotated[str, Strict(), Field(min_length=1, max_length=512)]
    code: RejectCode
    reason: Text
    offender: AgentId | None = None
    rejected_kind: Annotated[str, Strict(), Field(max_length=64)] | None = None
    payload_size: Count
    payload_sha256: Annotated[str, Strict(), Field(pattern=r"^[0-9a-f]{64}$")]
    received_at: Timestamp


MODELS: dict[str, type[Envelope]] = {
    model.model_fields["kind"].default: model
    for model in (Registration, CallForBids, Bid, Award, Schedule, Clock, GridState, MeterReport,
                  SettlementStatement, DaySummary, Rejection)
}
KINDS = tuple(MODELS)

Message = Annotated[Union[Registration, CallForBids, Bid, Award, Schedule, Clock, GridState, MeterReport,
                          SettlementStatement, DaySummary, Rejection], Field(discriminator="kind")]
MESSAGE_ADAPTER: TypeAdapter[Message] = TypeAdapter(Message)


def _schema(kind: str) -> dict:
    schema = MODELS[kind].model_json_schema(mode="serialization")
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "$id": f"urn:dmosim:{kind}:v{SCHEMA_VERSION}",
            **schema}


# JSON Schema (draft 2020-12) of each kind as it appears on the wire: every field required.
SCHEMAS: dict[str, dict] = {kind: _schema(kind) for kind in KINDS}


def json_schema(kind: str) -> dict:
    """The JSON Schema of one message kind (a fresh copy)."""
    if kind not in SCHEMAS:
        raise KeyError(f"unknown kind {kind!r}; kinds are {', '.join(KINDS)}")
    return _schema(kind)
