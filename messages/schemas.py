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

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, TypeAdapter, ValidationInfo, model_validator

from scenarios.horizon import HOURS
from scenarios.names import DMO, NAME_PATTERN, RESERVED_NAMES
from scenarios.network import MAX_BUSES, MAX_NAME_LENGTH

# 2: the clock says which day of how many (a run of several market days); 3: awards and statements name their
# settlement rule, and awards carry its price of a deviation; 4: every message is bound to its run (``run``) and
# its sender's process (``incarnation``), and the DMO answers every agent message with a receipt; 5: awards carry the
# clearing's congestion per hour, and an agent may report its realised day (``agent_day``); 6: a registration
# names the agent's bidding strategy; 7: on a feeder, registrations and awards name the agent's bus, awards carry
# their price's components, and ``network_hour`` publishes the feeder's hours; 8: on a feeder, a grid state carries
# the hour's operating envelope (``buses``, ``room_mw``); 9: each message an agent_day says the agent handled carries
# when it was taken up and how long the agent waited for its turn (``started_at``, ``turn_s``); 10: awards and
# network hours carry the loss component, network hours the clearing method and spilled generation; 11: a grid
# state's envelope is one-sided, a room above each award and one below (``import_room_mw``, ``export_room_mw``),
# and a network hour's plan says what binds (``limit_loading``, ``binding_facet``, ``line_shadow_price_per_mwh``,
# ``binding_voltage``, ``voltage_shadow_price_per_pu``)
SCHEMA_VERSION = 11
MAX_DAYS = 3660
MAX_SUBPERIODS = 60
MAX_BID_STEPS = 16
# The bid prices a call for bids allows by default, $/MWh: the DMO's, and what an agent tries a strategy against
PRICE_FLOOR = -1000.0
PRICE_CAP = 10_000.0
MAX_PIECES = 8
MAX_UNITS = 64
MAX_AGENTS = 1024
MAX_HANDLED = 1000  # entries of an agent_day's ``compute``: the messages of a day an agent handled, with room to spare
CENT = 0.01
KIND = "the message type: which schema the message follows and which key it travels on"

# Strict scalars: the wire never coerces between types.
Float = Annotated[float, Strict()]
NonNeg = Annotated[float, Strict(), Field(ge=0)]
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
                     "wrong_key", "unauthorised", "late", "duplicate", "wrong_day", "unregistered", "wrong_run",
                     "stale"]
REJECT_CODES: tuple[str, ...] = get_args(RejectCode)
Hourly = Annotated[tuple[Float, ...], Field(min_length=HOURS, max_length=HOURS)]
# Which limit bound an hour, as the clearing decided it (docs/market.md, "Price" and "Clearing on a feeder"):
# the substation's ("import", "export"), else on a feeder a line's or a bus voltage's, else "none".
Congestion = Literal["none", "import", "export", "line", "voltage"]
MarketDay = Annotated[str, Strict(), Field(pattern=r"^[0-9]{4}-[0-9]{2}-[0-9]{2}$")]
Piece = tuple[Float, Float]
BusName = Annotated[str, Strict(), Field(min_length=1, max_length=MAX_NAME_LENGTH)]  # as a feeder may name it
PerBus = Annotated[tuple[Float, ...], Field(min_length=1, max_length=MAX_BUSES)]
PerLine = PerBus  # a radial feeder has one line fewer than buses: checked per message
RuleName = Annotated[str, Strict(), Field(min_length=1, max_length=500)]
# The run's token: 32 hex digits the DMO draws when a run starts (empty in messages older than version 4).
RUN_TOKEN_PATTERN = r"^([0-9a-f]{32})?$"
Sha256 = Annotated[str, Strict(), Field(pattern=r"^[0-9a-f]{64}$")]
SETTLEMENT_RULE = ("the settlement rule the day is settled by, with every parameter, as docs/settlement.md names it "
                   "(e.g. \"paper:penalty=150,credit=0\"); null: the paper rule at penalty_per_mwh and credit_per_mwh "
                   "(as every day was settled before version 3)")


class _WireModel(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False,
                              json_schema_serialization_defaults_required=True)


def _check_length(values: tuple, subperiods: int, field: str) -> None:
    if len(values) != subperiods:
        raise ValueError(f"{field} has {len(values)} values, expected subperiods={subperiods}")


class Envelope(_WireModel):
    """Fields every message carries. ``seq`` and ``sent_at`` are stamped by the transport when published."""

    kind: str  # each message type narrows it to its literal tag; declared here so it comes first on the wire
    schema_version: Annotated[int, Strict(), Field(ge=1, le=SCHEMA_VERSION), Field(description=(
        f"version of the message schemas the sender wrote; this protocol is version {SCHEMA_VERSION} (a version 1 "
        "clock, which has no day and days, is read as day 1 of 1; a version 2 award or statement, which names no "
        "settlement rule, as settled by the paper rule)"))] = SCHEMA_VERSION
    sender: Annotated[Name, Field(description=(
        "\"dmo\" or the agent id; must be the owner of the key the message travels on"))]
    run: Annotated[str, Strict(), Field(pattern=RUN_TOKEN_PATTERN), Field(description=(
        "the run's token, 32 hex digits: the DMO draws it when the run starts and announces it on every message "
        "(its clock first); every other process copies it into each message it sends, and the DMO refuses a "
        "message with another (wrong_run): one recorded in another run, even under the same run id. Empty only "
        "in messages older than version 4"))] = ""
    incarnation: Annotated[Timestamp, Field(description=(
        "which process of the sender wrote the message: its start time, ns since the Unix epoch, the same on every "
        "message of one process. A restarted agent has a later one, so the DMO takes its new registration as a "
        "rejoin and refuses what an earlier process sent (stale). 0 only in messages older than version 4"))] = 0
    market_day: Annotated[MarketDay, Field(description="the market day the message belongs to, an ISO date YYYY-MM-DD")]
    seq: Annotated[Count, Field(description=(
        "the sender's sequence number: 0, 1, 2, ... over all messages of its process (its incarnation), stamped "
        "when sent; a message sent again (not acknowledged) keeps its number. The DMO takes an exact copy of a "
        "message it accepted as that message again (a receipt, nothing more), and refuses another payload under a "
        "number it has accepted (duplicate) or one 64 or more below the latest it accepted (late); a number below the "
        "latest but within 64 of it that was not accepted is taken (a message overtaken by a later one)"))] = 0
    sent_at: Annotated[Timestamp, Field(description=(
        "the sender's clock when sending, ns since the Unix epoch, stamped when sent"))] = 0

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

    kind: Annotated[Literal["registration"], Field(description=KIND)] = "registration"
    case: Annotated[str, Strict(), Field(min_length=1, max_length=64), Field(description=(
        "the name of the microgrid's case; informative, but a rejoining agent must give the same"))]
    max_import_mw: Annotated[NonNeg, Field(description=(
        "MW the microgrid can import at most (P_M max); a missing meter reading is settled at it, and a "
        "reading above it is refused"))]
    max_export_mw: Annotated[NonNeg, Field(description="MW the microgrid can export at most")]
    strategy: Annotated[Annotated[str, Strict(), Field(min_length=1, max_length=500)] | None, Field(description=(
        "the agent's bidding strategy as named, parameters included (docs/strategies.md), e.g. \"price-response\" "
        "or \"examples/strategy.py:Shaded:shade=0.9\"; informative, for the record; null: not said (an agent of "
        "another make, or older than version 6)"))] = None
    bus: Annotated[BusName | None, Field(description=(
        "the bus of the DMO's feeder the microgrid is connected at (docs/network.md); the DMO refuses a "
        "registration whose bus is not a bus of its feeder other than the substation, or not the bus the run "
        "placed the agent at. null: not said (a copper-plate market, or an agent older than version 7), and on a "
        "feeder the DMO then takes the run's placement"))] = None


# --- bidding ------------------------------------------------------------------------------------------------

class CallForBids(_FromDmo):
    """Phase 2, DMO -> all agents: the day's market terms; bids are due ``deadline_s`` after ``sent_at``."""

    kind: Annotated[Literal["call_for_bids"], Field(description=KIND)] = "call_for_bids"
    iso_price_per_mwh: Annotated[Hourly, Field(description=(
        "24 hourly upstream (ISO) prices, $/MWh, hour 1 first: the clearing price of every hour no feeder "
        "limit binds"))]
    price_floor_per_mwh: Annotated[Float, Field(description=(
        "lowest price a bid step should name, $/MWh (advisory: the DMO does not refuse a step below it)"))]
    price_cap_per_mwh: Annotated[Float, Field(description=(
        "highest price a bid step should name, $/MWh, at least the floor (advisory)"))]
    import_limit_mw: Annotated[NonNeg, Field(description=(
        "the feeder's import limit, MW: net imports of all agents above it congest the hour"))]
    export_limit_mw: Annotated[NonNeg, Field(description=(
        "the feeder's export limit, MW: net exports above it congest the hour"))]
    penalty_per_mwh: Annotated[NonNeg, Field(description=(
        "c: $ per MWh imported above the award, under the paper rule (under another rule, the c an agent that does "
        "not read deviation_cost schedules against)"))]
    credit_per_mwh: Annotated[NonNeg, Field(description=(
        "$ per MWh imported below the award (0: no credit), under the paper rule"))] = 0.0
    subperiods: Annotated[Subperiods, Field(description="K: metering sub-periods per hour, each 1/K h")]
    deadline_s: Annotated[float, Strict(), Field(gt=0, le=86_400), Field(description=(
        "bids are due this many seconds after sent_at"))]

    @model_validator(mode="after")
    def _price_band(self):
        if self.price_floor_per_mwh > self.price_cap_per_mwh:
            raise ValueError(f"price_floor_per_mwh {self.price_floor_per_mwh} exceeds price_cap_per_mwh "
                             f"{self.price_cap_per_mwh}")
        return self


class BidStep(_WireModel):
    """One price-quantity step: buy up to ``quantity_mw`` at up to ``price_per_mwh``; negative = sell at least at it."""

    price_per_mwh: Annotated[Float, Field(description=(
        "$/MWh: a purchase is accepted at clearing prices at or below it, a sale at or above it"))]
    quantity_mw: Annotated[Float, Field(description=(
        "MW: positive buys (imports) up to it, negative sells (exports) up to its magnitude; 0 trades nothing"))]


class Bid(_FromAgent):
    """Phase 2, agent -> DMO: the agent's price-quantity steps for each hour of the day."""

    kind: Annotated[Literal["bid"], Field(description=KIND)] = "bid"
    hours: Annotated[tuple[Annotated[tuple[BidStep, ...], Field(max_length=MAX_BID_STEPS)], ...],
                     Field(min_length=HOURS, max_length=HOURS, description=(
                         "24 lists of steps, hour 1 first, at most 16 steps each; an empty list is no offer that "
                         "hour"))]


# --- clearing -----------------------------------------------------------------------------------------------

class Award(_FromDmo):
    """Phase 3, DMO -> one agent: its hourly award P_sch, the clearing prices and the settlement terms."""

    kind: Annotated[Literal["award"], Field(description=KIND)] = "award"
    agent: Annotated[AgentId, Field(description="the agent awarded (the key names it too)")]
    p_sch_mw: Annotated[Hourly, Field(description=(
        "24 hourly awards P_sch, MW, hour 1 first; positive imports, negative exports"))]
    clearing_price_per_mwh: Annotated[Hourly, Field(description=(
        "24 hourly clearing prices, $/MWh: the agent's energy is settled at them. On a feeder, its own bus's prices "
        "(the DLMP: energy + loss + congestion + voltage, docs/market.md)"))]
    bus: Annotated[BusName | None, Field(description=(
        "on a feeder, the bus the agent is awarded at; null on the copper plate (and before version 7)"))] = None
    energy_price_per_mwh: Annotated[Hourly | None, Field(description=(
        "on a feeder, the energy component of the agent's prices: the substation's price, the same at every bus; "
        "null on the copper plate"))] = None
    loss_price_per_mwh: Annotated[Hourly | None, Field(description=(
        "on a feeder, the loss component at the agent's bus (what the losses its MW adds cost at the energy price; "
        "0 on a feeder cleared on LinDistFlow); null on the copper plate (and before version 10)"))] = None
    congestion_price_per_mwh: Annotated[Hourly | None, Field(description=(
        "on a feeder, the congestion component at the agent's bus (what binding line limits add); null on the "
        "copper plate"))] = None
    voltage_price_per_mwh: Annotated[Hourly | None, Field(description=(
        "on a feeder, the voltage component at the agent's bus (what binding voltage limits add); null on the "
        "copper plate"))] = None
    penalty_per_mwh: Annotated[NonNeg, Field(description=(
        "c: $ per MWh imported above the award, under the paper rule (under another rule, the c an agent that does "
        "not read deviation_cost schedules against)"))]
    credit_per_mwh: Annotated[NonNeg, Field(description=(
        "$ per MWh imported below the award (0: no credit), under the paper rule"))] = 0.0
    subperiods: Annotated[Subperiods, Field(description=(
        "K: metering sub-periods per hour; each meter report carries K readings"))]
    rules_version: Annotated[int, Strict(), Field(ge=1, le=10_000), Field(description=(
        "the version of the settlement rules the day is settled by"))]
    rules: Annotated[str, Strict(), Field(max_length=4000), Field(description=(
        "the settlement rules, in words"))]
    settlement_rule: Annotated[RuleName | None, Field(description=SETTLEMENT_RULE)] = None
    deviation_cost: Annotated[tuple[Annotated[tuple[Piece, ...], Field(min_length=1, max_length=MAX_PIECES)], ...]
                              | None, Field(min_length=HOURS, max_length=HOURS), Field(description=(
        "what the rule charges in each hour for a deviation d = P_M - P_sch (MW) held through it, as 24 hourly "
        "lists of at most 8 pieces [slope $/MWh, intercept $/h]: the charge is max(slope d + intercept) $/h; "
        "null when the rule cannot be written so (a rule of the user's own), and an agent then schedules against "
        "the paper's term at penalty_per_mwh"))] = None
    congestion: Annotated[tuple[Congestion, ...] | None, Field(min_length=HOURS, max_length=HOURS), Field(
        description=(
            "24 hourly congestion states, hour 1 first, as the clearing decided them (docs/market.md): \"import\" "
            "where the net import the ISO price calls for exceeds the feeder's import limit, \"export\" where the "
            "net export exceeds its export limit; on a feeder (a network clearing), else \"line\" where a line's "
            "thermal limit binds and else \"voltage\" where a bus's voltage limit does; else \"none\" (bids summing "
            "exactly to a limit do not congest it); the same for every agent. null only in awards older than "
            "version 5"))] = None


# --- scheduling ---------------------------------------------------------------------------------------------

class ACCheck(_WireModel):
    """The AC power flow of one hour of a feeder (docs/network.md, "The AC check"); every number null, every name
    empty and the one violation "no AC solution" when it did not converge."""

    converged: Annotated[Bool, Field(description="whether the Newton-Raphson power flow converged")]
    v_min_pu: Annotated[Float | None, Field(description="the lowest bus voltage, p.u.")]
    v_min_bus: Annotated[Annotated[str, Strict(), Field(max_length=MAX_NAME_LENGTH)], Field(description=(
        "the bus of the lowest voltage"))]
    v_max_pu: Annotated[Float | None, Field(description="the highest bus voltage, p.u.")]
    v_max_bus: Annotated[Annotated[str, Strict(), Field(max_length=MAX_NAME_LENGTH)], Field(description=(
        "the bus of the highest voltage"))]
    max_loading: Annotated[NonNeg | None, Field(description=(
        "the most loaded line's apparent power at its sending end over its limit"))]
    max_loading_line: Annotated[Annotated[str, Strict(), Field(max_length=130)], Field(description=(
        "the most loaded line, \"from-to\""))]
    voltage_error_pu: Annotated[NonNeg | None, Field(description="max over buses of |V LinDistFlow - V AC|, p.u.")]
    flow_error_mw: Annotated[NonNeg | None, Field(description=(
        "max over lines of |P LinDistFlow - P AC| at the line's substation end, MW"))]
    losses_mw: Annotated[Float | None, Field(description="the feeder's losses, MW")]
    substation_mw: Annotated[Float | None, Field(description="the AC import at the substation, MW")]
    violations: Annotated[tuple[Text, ...], Field(max_length=MAX_BUSES * 2), Field(description=(
        "each limit the AC flow breaks, one short line each, e.g. \"undervoltage 17 0.9491<0.95\", "
        "\"overload 2-3 104.2%\" (against the feeder's own limits, not the clearing's margin)"))]
    margin: Annotated[NonNeg, Field(description=(
        "the voltage margin, p.u., the clearing kept inside the limits: voltage_error_pu at or below it means the "
        "margin covered what LinDistFlow neglects that hour"))]


class NetworkHour(_FromDmo):
    """Clearing and settlement, DMO -> all, on a feeder only: one hour of the feeder as planned (after clearing,
    the hour's awards) or as realised (after real time, the hour's metered transfers), with its AC check."""

    kind: Annotated[Literal["network_hour"], Field(description=KIND)] = "network_hour"
    hour: Annotated[Hour, Field(description="the hour, 1..24")]
    stage: Annotated[Literal["plan", "realised"], Field(description=(
        "\"plan\": the awards as cleared; \"realised\": the hour's mean metered transfers (a missing reading "
        "counts as 0 here: the grid, not the settlement)"))]
    network: Annotated[Annotated[str, Strict(), Field(min_length=1, max_length=MAX_NAME_LENGTH)], Field(description=(
        "the feeder's name"))]
    buses: Annotated[tuple[BusName, ...], Field(min_length=2, max_length=MAX_BUSES), Field(description=(
        "the feeder's buses, in its order; every per-bus field follows it"))]
    substation: Annotated[BusName, Field(description=(
        "the substation bus, one of buses: where the DMO trades with the ISO, held at its voltage"))]
    lines: Annotated[tuple[Annotated[str, Strict(), Field(min_length=3, max_length=130)], ...],
                     Field(min_length=1, max_length=MAX_BUSES), Field(description=(
        "the feeder's lines as \"from-to\" (from the substation's side), in its order; line_loading follows it"))]
    substation_mw: Annotated[Float, Field(description=(
        "the DMO's position at the substation by LinDistFlow, MW, + import: in the plan, its bid to the ISO "
        "(paper Fig. 1)"))]
    injection_mw: Annotated[PerBus, Field(description="the microgrids' net import at each bus, MW")]
    voltage_pu: Annotated[PerBus, Field(description="each bus's voltage by LinDistFlow, p.u.")]
    line_loading: Annotated[tuple[Float, ...], Field(min_length=1, max_length=MAX_BUSES), Field(description=(
        "each line's apparent power by LinDistFlow over its limit, lines in the feeder's order"))]
    energy_price_per_mwh: Annotated[Float | None, Field(description=(
        "the substation's price, $/MWh (plan only; null when realised)"))] = None
    clearing: Annotated[Literal["lindistflow", "ac"] | None, Field(description=(
        "how the hour was cleared: on LinDistFlow or on the AC flow linearised at its own plan (docs/market.md, "
        "\"AC-faithful clearing\"); plan only (null when realised, and before version 10)"))] = None
    bus_price_per_mwh: Annotated[PerBus | None, Field(description=(
        "each bus's price (DLMP), $/MWh: energy + loss + congestion + voltage (plan only)"))] = None
    loss_price_per_mwh: Annotated[PerBus | None, Field(description=(
        "each bus's loss component, $/MWh: 0 on LinDistFlow (plan only; null before version 10)"))] = None
    congestion_price_per_mwh: Annotated[PerBus | None, Field(description=(
        "each bus's congestion component, $/MWh (plan only)"))] = None
    voltage_price_per_mwh: Annotated[PerBus | None, Field(description=(
        "each bus's voltage component, $/MWh (plan only)"))] = None
    shed_mw: Annotated[PerBus | None, Field(description=(
        "fixed load the clearing shed at each bus to stay within the limits, MW, at the value of lost load "
        "(docs/market.md; plan only)"))] = None
    spilled_mw: Annotated[PerBus | None, Field(description=(
        "fixed generation the clearing spilled at each bus to stay within the limits, MW, at the spill price "
        "(docs/market.md; plan only; null before version 10)"))] = None
    limit_loading: Annotated[PerLine | None, Field(description=(
        "each line's loading as the clearing limits it: its largest facet n_P P + n_Q Q over its rating, 1 where a "
        "facet binds (line_loading, |S| over the rating, is 0.92 to 1 there: docs/market.md), in the clearing's "
        "flow (the AC flow's for \"ac\"); plan only (null when realised, and before version 11)"))] = None
    binding_facet: Annotated[Annotated[tuple[Annotated[int, Strict(), Field(ge=0, le=7)] | None, ...],
                                       Field(min_length=1, max_length=MAX_BUSES)] | None, Field(description=(
        "per line, the facet (0..7) of its limit the clearing holds at its bound, null where none (docs/market.md, "
        "\"What binds\"); plan only (null when realised, and before version 11)"))] = None
    line_shadow_price_per_mwh: Annotated[PerLine | None, Field(description=(
        "per line, what a MW more of its rating would add to the hour's welfare, $/h per MW: the dual of its binding "
        "facets, 0 where none binds; plan only (null when realised, and before version 11)"))] = None
    binding_voltage: Annotated[Annotated[tuple[Literal["v_min", "v_max"] | None, ...],
                                         Field(min_length=1, max_length=MAX_BUSES)] | None, Field(description=(
        "per bus, the voltage limit the clearing holds it at, null where none; plan only (null when realised, and "
        "before version 11)"))] = None
    voltage_shadow_price_per_pu: Annotated[PerBus | None, Field(description=(
        "per bus, what 1 p.u. more room at its binding voltage limit would add to the hour's welfare, $/h per p.u. "
        "of voltage, 0 where none binds; plan only (null when realised, and before version 11)"))] = None
    ac: Annotated[ACCheck, Field(description="the hour's AC power flow")]

    @model_validator(mode="after")
    def _per_bus(self):
        n = len(self.buses)
        if self.substation not in self.buses:
            raise ValueError(f"substation {self.substation!r} is not one of the buses")
        for name in ("injection_mw", "voltage_pu", "bus_price_per_mwh", "loss_price_per_mwh",
                     "congestion_price_per_mwh", "voltage_price_per_mwh", "shed_mw", "spilled_mw", "binding_voltage",
                     "voltage_shadow_price_per_pu"):
            values = getattr(self, name)
            if values is not None and len(values) != n:
                raise ValueError(f"{name} has {len(values)} values for {n} buses")
        if len(self.lines) != n - 1 or len(self.line_loading) != n - 1:
            raise ValueError(f"a radial feeder of {n} buses has {n - 1} lines; lines and line_loading give "
                             f"{len(self.lines)} and {len(self.line_loading)}")
        for name in ("limit_loading", "binding_facet", "line_shadow_price_per_mwh"):
            values = getattr(self, name)
            if values is not None and len(values) != n - 1:
                raise ValueError(f"{name} has {len(values)} values for {n - 1} lines")
        return self


class Schedule(_FromAgent):
    """Phase 4, agent -> DMO: the day-ahead schedule the agent solved against its award."""

    kind: Annotated[Literal["schedule"], Field(description=KIND)] = "schedule"
    status: Annotated[str, Strict(), Field(min_length=1, max_length=64), Field(description=(
        "free text, for the log: the DMO reads nothing from it; dmosim agents send \"optimal\" or \"time_limit\""))]
    commitment: Annotated[dict[Annotated[str, Strict(), Field(pattern=NAME_PATTERN)],
                               Annotated[tuple[Literal[0, 1], ...], Field(min_length=HOURS, max_length=HOURS)]],
                          Field(max_length=MAX_UNITS,
                                description="unit name -> 24 hourly values, 1 committed, 0 not (at most 64 units)")]
    expected_cost: Annotated[Float, Field(description="the schedule's expected cost of the day, $")]
    p_m_expected_mw: Annotated[Hourly, Field(description="24 hourly expected transfers P_M, MW; positive imports")]
    scenarios: Annotated[int, Strict(), Field(ge=1, le=100_000), Field(description=(
        "how many scenarios the schedule was solved on"))]
    mip_gap: Annotated[Annotated[float, Strict(), Field(ge=0)] | None, Field(description=(
        "the solve's certified relative gap, or null"))] = None

    @property
    def stopped_short(self) -> bool:
        """Whether the solve stopped short of its gap: any status but "optimal" (a time limit, most often)."""
        return self.status != "optimal"


# --- real-time operation ------------------------------------------------------------------------------------

class Clock(_FromDmo):
    """DMO -> all: the simulated clock; a new phase (and, in real time, a new hour) starts now."""

    kind: Annotated[Literal["clock"], Field(description=KIND)] = "clock"
    phase: Annotated[Phase, Field(description="the phase starting now")]
    hour: Annotated[Hour | None, Field(description=(
        "the real-time hour starting now, 1..24 (hour 1 is midnight to 1:00); null outside realtime"))] = None
    deadline_s: Annotated[float, Strict(), Field(gt=0, le=86_400), Field(description=(
        "seconds until the phase (or hour) ends: answers after it are late"))]
    day: Annotated[int, Strict(), Field(ge=1, le=MAX_DAYS, description=(
        "which market day of the run this is, 1 first; registration happens once, on day 1"))]
    days: Annotated[int, Strict(), Field(ge=1, le=MAX_DAYS, description=(
        "how many market days the run has: after the settlement of the last one the run is over"))]

    @model_validator(mode="after")
    def _hour_in_realtime(self):
        if (self.phase == "realtime") != (self.hour is not None):
            raise ValueError("hour is required in phase realtime and only there")
        if self.day > self.days:
            raise ValueError(f"day {self.day} is past the run's {self.days} days")
        return self


class GridState(_FromDmo):
    """Phase 5, DMO -> all, once per hour: the grid's realised state; connected False = islanded (U = 0). On a
    feeder, also the hour's operating envelope: how far each microgrid may stray above and below its award."""

    kind: Annotated[Literal["grid_state"], Field(description=KIND)] = "grid_state"
    hour: Annotated[Hour, Field(description="the hour this state holds for, 1..24")]
    subperiods: Annotated[Subperiods, Field(description="K: sub-periods per hour")]
    connected: Annotated[tuple[Bool, ...], Field(min_length=1, max_length=MAX_SUBPERIODS), Field(description=(
        "K booleans, one per sub-period: true grid-connected, false islanded (U = 0: P_M must be 0)"))]
    buses: Annotated[tuple[BusName, ...], Field(max_length=MAX_BUSES), Field(description=(
        "on a feeder, every bus of the DMO's feeder, in its order, each once: import_room_mw and export_room_mw "
        "follow it; empty on the copper plate (and before version 8)"))] = ()
    import_room_mw: Annotated[tuple[NonNeg, ...], Field(max_length=MAX_BUSES), Field(description=(
        "the hour's operating envelope above the awards, one room per bus of buses (docs/network.md, \"Operating "
        "envelopes\"): in the hour's grid-connected sub-periods each microgrid at the bus keeps its P_M at most its "
        "award plus this many MW, and the feeder's limits then hold whatever the others do within theirs; 0 at a "
        "bus without a microgrid. Empty on the copper plate; before version 11, the one room either way"))] = ()
    export_room_mw: Annotated[tuple[NonNeg, ...], Field(max_length=MAX_BUSES), Field(description=(
        "the hour's operating envelope below the awards, as import_room_mw: each microgrid at the bus keeps its P_M "
        "at least its award less this many MW"))] = ()

    @model_validator(mode="after")
    def _lengths(self):
        _check_length(self.connected, self.subperiods, "connected")
        for name in ("import_room_mw", "export_room_mw"):
            if len(getattr(self, name)) != len(self.buses):
                raise ValueError(f"{name} has {len(getattr(self, name))} values for {len(self.buses)} buses")
        if len(set(self.buses)) != len(self.buses):
            raise ValueError("buses names a bus more than once")
        return self


class MeterReport(_FromAgent):
    """Phase 5, agent -> DMO, once per hour: metered transfer P_M per sub-period and its deviation P_M - P_sch."""

    kind: Annotated[Literal["meter_report"], Field(description=KIND)] = "meter_report"
    hour: Annotated[Hour, Field(description=(
        "the hour metered, 1..24: the hour the DMO's clock and grid state announced"))]
    subperiods: Annotated[Subperiods, Field(description="K, as in the award")]
    p_m_mw: Annotated[tuple[Float, ...], Field(min_length=1, max_length=MAX_SUBPERIODS), Field(description=(
        "K metered transfers P_M, MW, one per sub-period; positive imports; none above the registered "
        "max_import_mw nor below -max_export_mw, and 0 in every sub-period the hour's grid state says is islanded "
        "(each within 1e-9 MW)"))]
    deviation_mw: Annotated[tuple[Float, ...], Field(min_length=1, max_length=MAX_SUBPERIODS), Field(description=(
        "K deviations P_M - P_sch, MW; informative: settlement reads p_m_mw"))]

    @model_validator(mode="after")
    def _lengths(self):
        _check_length(self.p_m_mw, self.subperiods, "p_m_mw")
        _check_length(self.deviation_mw, self.subperiods, "deviation_mw")
        return self


class HandlingTime(_WireModel):
    """The agent's computation on one message of the DMO's it handled: from taking it up to sending its answer (or,
    for a message it does not answer, to being done with it)."""

    kind: Annotated[Literal["clock", "call_for_bids", "award", "grid_state", "settlement_statement", "day_summary"],
                    Field(description="the kind of the DMO's message handled")]
    hour: Annotated[Hour | None, Field(description="its hour (a clock's or grid state's in real time), or null")]
    wall_s: Annotated[NonNeg, Field(description="wall-clock seconds")]
    cpu_s: Annotated[NonNeg, Field(description="CPU seconds of the thread that handled it (not other agents "
                                                "sharing its process)")]
    started_at: Annotated[Annotated[int, Strict(), Field(ge=0, lt=2**63)] | None, Field(description=(
        "when it took the message up, ns since the Unix epoch on the agent's clock; null before version 9"))]
    turn_s: Annotated[NonNeg, Field(description=(
        "seconds of wall_s it waited for its turn to compute, among agents forked from one host that take turns "
        "(0 otherwise, and before version 9): it computed from started_at + turn_s to started_at + wall_s"))]

    @model_validator(mode="after")
    def _turn_within_wall(self):
        if self.turn_s > self.wall_s:
            raise ValueError(f"turn_s {self.turn_s} is a part of wall_s {self.wall_s}, not more")
        return self


Counts = Annotated[dict[Annotated[str, Strict(), Field(min_length=1, max_length=64)], Count], Field(max_length=64)]


class MessageCounts(_WireModel):
    """What an agent's process did with messages since it started (its incarnation), as its day was operated."""

    published: Annotated[Count, Field(description="payloads it published, sends again included")]
    received: Annotated[Count, Field(description="valid messages it received")]
    rejected: Annotated[Counts, Field(description="received payloads it refused, by code")]
    handler_errors: Annotated[Count, Field(description="messages whose handling failed")]
    ignored: Annotated[Counts, Field(description=(
        "messages it handled as no-ops, by why (e.g. award_again: the same award again)"))]
    sent_again: Annotated[Count, Field(description="payloads it sent again for want of a receipt")]
    asked: Annotated[Count, Field(description="messages it asked the DMO for after a silence, and handled")]
    faults_injected: Annotated[Counts, Field(description="message faults its bus injected, by kind (e.g. drop)")]


class MidnightUnit(_WireModel):
    """One unit as the operated day ended: what it carries into the next day."""

    on: Annotated[Bool, Field(description="whether it is committed in hour 24")]
    output_mw: Annotated[Float, Field(description="its output in the last sub-period, MW")]
    hours: Annotated[int, Strict(), Field(ge=1, le=HOURS), Field(description=(
        "the whole hours it has been in that state, 24 meaning at least a day"))]


class AgentDay(_FromAgent):
    """Phase 5, agent -> DMO, once a day after its last meter report: the agent's own account of its operated day,
    what the DMO cannot see (its cost, curtailment, state at midnight, computation and message counts). Informational:
    it never changes a settlement, and an agent that does not send it takes part all the same."""

    kind: Annotated[Literal["agent_day"], Field(description=KIND)] = "agent_day"
    generation: Annotated[Float, Field(description="$: its units' generation cost over the operated day")]
    startup: Annotated[Float, Field(description="$: its units' start-up cost")]
    curtailment: Annotated[Float, Field(description="$: the cost of the load it curtailed")]
    penalty: Annotated[Float, Field(description=(
        "$: its deviations from the award priced as it scheduled against them (its own reckoning, not the "
        "statement's)"))]
    total: Annotated[Float, Field(description="$: generation + startup + curtailment + penalty")]
    curtailment_mwh: Annotated[NonNeg, Field(description="MWh of load it curtailed")]
    deviation_mwh: Annotated[NonNeg, Field(description=(
        "MWh it imported above its award, the sum of max(P_M - P_sch, 0) dt"))]
    units: Annotated[dict[Annotated[str, Strict(), Field(pattern=NAME_PATTERN)], MidnightUnit],
                     Field(max_length=MAX_UNITS, description=(
                         "unit name -> its state at midnight, which the next day starts from"))]
    stored_mwh: Annotated[Annotated[float, Strict(), Field(ge=0)] | None, Field(description=(
        "the energy in its storage at midnight, MWh, or null without a storage"))]
    compute: Annotated[tuple[HandlingTime, ...], Field(max_length=MAX_HANDLED, description=(
        "the messages of the day it handled up to its last meter report, in order, each with its computation "
        "(at most 1000: the first ones)"))]
    messages: Annotated[MessageCounts, Field(description="its process's message counts as the day was operated")]

    @model_validator(mode="after")
    def _adds_up(self):
        _check_sum(self.total, self.generation + self.startup + self.curtailment + self.penalty, "total")
        return self


# --- settlement ---------------------------------------------------------------------------------------------

class StatementLine(_WireModel):
    """One hour of a statement. ``import_mwh`` is the settled import (metered sub-periods as reported, missing ones
    by the missing-report rule); ``deviation_mwh`` the sum of max(P_M - P_sch, 0) dt, ``under_import_mwh`` the sum
    of max(P_sch - P_M, 0) dt; total = energy_charge + deviation_penalty - deviation_credit."""

    hour: Annotated[Hour, Field(description="the hour, 1..24")]
    p_sch_mw: Annotated[Float, Field(description="the award P_sch, MW")]
    clearing_price_per_mwh: Annotated[Float, Field(description="the clearing price, $/MWh")]
    energy_charge: Annotated[Float, Field(description="$: clearing price x award x 1 h")]
    import_mwh: Annotated[Float, Field(description=(
        "the settled import, MWh: metered sub-periods as reported, missing ones at the registered max import"))]
    deviation_mwh: Annotated[NonNeg, Field(description="MWh: the sum over sub-periods of max(P_M - P_sch, 0) dt")]
    under_import_mwh: Annotated[NonNeg, Field(description=(
        "MWh: the sum over metered sub-periods of max(P_sch - P_M, 0) dt"))]
    deviation_penalty: Annotated[NonNeg, Field(description="$: penalty rate x deviation_mwh")]
    deviation_credit: Annotated[NonNeg, Field(description="$: credit rate x under_import_mwh")]
    total: Annotated[Float, Field(description="$: energy_charge + deviation_penalty - deviation_credit")]
    missing: Annotated[Bool, Field(description=(
        "true if a sub-period of the hour was settled by the missing-report rule"))]
    missing_subperiods: Annotated[int, Strict(), Field(ge=0, le=MAX_SUBPERIODS), Field(description=(
        "how many sub-periods were"))]

    @model_validator(mode="after")
    def _adds_up(self):
        _check_sum(self.total, self.energy_charge + self.deviation_penalty - self.deviation_credit, "total")
        return self


class SettlementStatement(_FromDmo):
    """Phase 6, DMO -> one agent: its itemised bill, 24 lines and their totals (each the sum of its lines)."""

    kind: Annotated[Literal["settlement_statement"], Field(description=KIND)] = "settlement_statement"
    agent: Annotated[AgentId, Field(description="the agent settled (the key names it too)")]
    penalty_per_mwh: Annotated[NonNeg, Field(description="the penalty rate applied under the paper rule, $/MWh")]
    credit_per_mwh: Annotated[NonNeg, Field(description="the credit rate applied under the paper rule, $/MWh")]
    rules_version: Annotated[int, Strict(), Field(ge=1, le=10_000), Field(description=(
        "the version of the settlement rules applied"))]
    settlement_rule: Annotated[RuleName | None, Field(description=SETTLEMENT_RULE)] = None
    lines: Annotated[tuple[StatementLine, ...], Field(min_length=HOURS, max_length=HOURS), Field(description=(
        "24 lines, hours 1..24 in order"))]
    energy_charge: Annotated[Float, Field(description="$: the sum of the lines'")]
    deviation_penalty: Annotated[NonNeg, Field(description="$: the sum of the lines'")]
    deviation_credit: Annotated[NonNeg, Field(description="$: the sum of the lines'")]
    total: Annotated[Float, Field(description="$: the sum of the lines', what the agent owes (negative: is owed)")]
    missing_subperiods: Annotated[Count, Field(description="the sum of the lines'")]

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
    """One agent's line of the day summary: the totals of its settlement statement."""

    energy_charge: Annotated[Float, Field(description="$, as in the agent's statement")]
    deviation_penalty: Annotated[NonNeg, Field(description="$, as in the agent's statement")]
    deviation_credit: Annotated[NonNeg, Field(description="$, as in the agent's statement")]
    total: Annotated[Float, Field(description="$, as in the agent's statement")]


class Incident(_WireModel):
    """Something that went wrong during the day: a late, missing or vanished agent, a rejected message."""

    agent: Annotated[AgentId | None, Field(description="the agent concerned, or null")]
    phase: Annotated[Phase, Field(description="the phase it happened in")]
    hour: Annotated[Hour | None, Field(description="the real-time hour it happened in, or null")]
    reason: Annotated[Text, Field(description="what happened, one line")]


class DaySummary(_FromDmo):
    """Phase 6, DMO -> all: the day's outcome, once every statement is out."""

    kind: Annotated[Literal["day_summary"], Field(description=KIND)] = "day_summary"
    agents: Annotated[tuple[AgentId, ...], Field(max_length=MAX_AGENTS), Field(description=(
        "the registered agents, sorted"))]
    clearing_price_per_mwh: Annotated[Hourly, Field(description="24 hourly clearing prices, $/MWh")]
    totals: Annotated[dict[Annotated[str, Strict(), Field(pattern=NAME_PATTERN)], AgentTotals],
                      Field(max_length=MAX_AGENTS,
                            description="agent -> the totals of its statement; registered agents only")]
    rejected_messages: Annotated[Count, Field(description="how many received payloads the DMO refused during the day")]
    incidents: Annotated[tuple[Incident, ...], Field(max_length=10_000), Field(description=(
        "what went wrong during the day: late, missing or vanished agents, rejections (at most 10,000)"))]

    @model_validator(mode="after")
    def _known_agents(self):
        unknown = sorted(set(self.totals) - set(self.agents))
        if unknown:
            raise ValueError(f"totals name agents not in agents: {', '.join(unknown)}")
        return self


class Rejection(_FromDmo):
    """DMO -> the recording: a received payload was refused; says which, where and why, so the recording keeps it
    (agents do not hear it: each learns of its own refusals from its receipts)."""

    kind: Annotated[Literal["rejection"], Field(description=KIND)] = "rejection"
    key: Annotated[str, Strict(), Field(min_length=1, max_length=512), Field(description=(
        "the key the refused payload arrived on"))]
    code: Annotated[RejectCode, Field(description="why, as a category")]
    reason: Annotated[Text, Field(description="why, one line")]
    offender: Annotated[AgentId | None, Field(description="the agent the key names, or null")] = None
    rejected_kind: Annotated[Annotated[str, Strict(), Field(max_length=64)] | None, Field(description=(
        "the kind the payload claimed, or null"))] = None
    payload_size: Annotated[Count, Field(description="the payload's size, bytes")]
    payload_sha256: Annotated[Sha256, Field(description=(
        "SHA-256, hex, of the payload's bytes exactly as the DMO received them"))]
    received_at: Annotated[Timestamp, Field(description="the DMO's clock on receipt, ns since the Unix epoch")]


class Receipt(_FromDmo):
    """DMO -> one agent: what became of one payload it received from that agent, accepted or refused. An agent sends
    each registration, bid, schedule, meter report and agent_day again until its receipt comes (docs/protocol.md)."""

    kind: Annotated[Literal["receipt"], Field(description=KIND)] = "receipt"
    agent: Annotated[AgentId, Field(description="the agent whose payload this is (the key names it too)")]
    payload_sha256: Annotated[Sha256, Field(description=(
        "SHA-256, hex, of the payload's bytes exactly as the DMO received them: the sender matches it against "
        "what it sent"))]
    received_kind: Annotated[Annotated[str, Strict(), Field(max_length=64)] | None, Field(description=(
        "the kind the payload claimed, or null if it could not be read"))]
    received_seq: Annotated[Count | None, Field(description="the payload's seq, or null if it could not be read")]
    accepted: Annotated[Bool, Field(description=(
        "true: accepted (or an exact copy of a payload accepted before: nothing more happens); false: refused, "
        "for good: sending it again changes nothing, a corrected message with a new seq may be sent while its "
        "phase (or hour) is open"))]
    code: Annotated[RejectCode | None, Field(description="why it was refused, as a category; null if accepted")]
    reason: Annotated[Text, Field(description="why it was refused, one line; empty if accepted")]

    @model_validator(mode="after")
    def _outcome(self):
        if self.accepted != (self.code is None):
            raise ValueError("a receipt has a code if and only if the payload was refused")
        return self


MODELS: dict[str, type[Envelope]] = {
    model.model_fields["kind"].default: model
    for model in (Registration, CallForBids, Bid, Award, Schedule, Clock, GridState, MeterReport, AgentDay,
                  NetworkHour, SettlementStatement, DaySummary, Rejection, Receipt)
}
KINDS = tuple(MODELS)

Message = Annotated[Union[Registration, CallForBids, Bid, Award, Schedule, Clock, GridState, MeterReport, AgentDay,
                          NetworkHour, SettlementStatement, DaySummary, Rejection, Receipt], Field(discriminator="kind")]
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
