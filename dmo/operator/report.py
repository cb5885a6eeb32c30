"""The DMO's part of a run's result as typed models: each settled day (``DayReport``) and the run's days together
(``DmoReport``), what ``dmosim dmo --result`` writes and ``dmosim run`` extends (docs/experiments.md, "The result").

A field whose default is None is left out of the JSON when it is None (a one-day run has no ``market_days``, a
longer one no ``day``); a field without a default is always written, null where its type allows it. So the JSON
keeps the keys it had as a dict.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, SerializerFunctionWrapHandler, model_serializer

from messages.schemas import HandlingTime, Incident, MessageCounts, MidnightUnit

Dollars = Annotated[float, Field(description="$")]
Mwh = Annotated[float, Field(description="MWh")]


class ResultModel(BaseModel):
    """A part of a run's result: frozen, no key it does not declare, and a None default left out of the JSON."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    @model_serializer(mode="wrap")
    def _leave_out_absent(self, handler: SerializerFunctionWrapHandler):
        data = handler(self)
        fields = type(self).model_fields
        return {k: v for k, v in data.items() if v is not None or k not in fields or fields[k].is_required()}


class AgentSettlement(ResultModel):
    """An agent's statement summed over its hours (of a day, or of the run's days)."""

    energy_charge: Dollars
    deviation_penalty: Dollars
    credit: Dollars
    total: Dollars = Field(description="$: energy_charge + deviation_penalty - credit")
    award_mwh: Mwh
    import_mwh: Mwh
    deviation_mwh: Mwh
    missing_subperiods: int = Field(description="metering sub-periods the DMO had no reading of")


class SettledTotals(ResultModel):
    """The day summary's totals over every statement of the day (``DayTotals``)."""

    agents: list[str] = Field(description="the agents settled")
    energy_charge: Dollars
    deviation_penalty: Dollars
    credit: Dollars
    total: Dollars
    deviation_mwh: Mwh
    missing_subperiods: int
    agents_without_meter: list[str] = Field(description="agents that sent no meter data at all")


class StoppedShort(ResultModel):
    """A schedule whose solve stopped short of its gap (any status but optimal: a time limit, most often)."""

    agent: str
    status: str = Field(description="the solve's status")
    mip_gap: float | None = Field(description="the certified gap, or null where the solve certified none")
    market_day: str | None = Field(None, description="its market day (in the run's list of a longer run)")


class DatedIncident(Incident):
    """An incident of the run's list: with its market day in a run of several days."""

    market_day: str | None = Field(None, description="the market day it happened on (a run of several days)")

    @model_serializer(mode="wrap")
    def _leave_out_absent(self, handler: SerializerFunctionWrapHandler):
        data = handler(self)
        return data if self.market_day is not None else {k: v for k, v in data.items() if k != "market_day"}


class ReportedDay(ResultModel):
    """An agent's realised day as its ``agent_day`` message said (docs/protocol.md), with the run's day."""

    day: int | None = Field(description="the run's day (1-based), null for a market day the DMO did not settle")
    market_day: str
    generation: Dollars
    startup: Dollars
    curtailment: Dollars
    penalty: Dollars
    total: Dollars
    curtailment_mwh: Mwh
    deviation_mwh: Mwh
    units: dict[str, MidnightUnit] = Field(description="unit -> its state at midnight")
    stored_mwh: float | None = Field(description="MWh in its storage at midnight, null without one")
    compute: list[HandlingTime] = Field(description="each message of the day it handled, with its computation")
    messages: MessageCounts = Field(description="its process's message counts")


class DayReport(ResultModel):
    """One settled market day: prices, awards, each agent's settlement, incidents and counts."""

    day: int = Field(description="the run's day, 1-based")
    market_day: str = Field(description="YYYY-MM-DD")
    islanded_hours: list[int] = Field(description="the hours (1-24) the grid was islanded")
    clearing_prices: list[float] = Field(description="24 hourly clearing prices, $/MWh")
    congestion: list[str] = Field(description="24: which limit bound the hour's clearing (none, import, export...)")
    awards: dict[str, list[float]] = Field(description="agent -> 24 hourly awards, MW")
    settlement: dict[str, AgentSettlement] = Field(description="agent -> its statement summed")
    day_summary: SettledTotals
    expected_cost: dict[str, float] = Field(description="agent -> its schedule's expected cost, $")
    schedules_stopped_short: list[StoppedShort]
    rejected_messages: int = Field(description="received payloads the DMO refused")
    rejected_by_code: dict[str, int] = Field(description="refusals by code")
    accepted_messages: dict[str, int] = Field(description="accepted payloads by kind")
    received_again: int = Field(description="exact copies of accepted payloads, sent again for want of a receipt")
    dropped_messages: dict[str, int] = Field(description="agent -> payloads dropped unread, over its budget")
    locked_out: list[str] = Field(description="agents a process of which spoke and was not admitted")
    incidents: list[Incident]
    phase_s: dict[str, float] = Field(description="seconds per phase")


class DmoReport(ResultModel):
    """The DMO's result of a run: every day, and the run's figures at the top (a one-day run's are its day's; a
    longer one's are hourly values day after day, settlements summed, incidents of every day with their market day,
    ``islanded_hours`` per day)."""

    run_id: str
    agents: list[str] = Field(description="the registered agents")
    days: list[DayReport] = Field(description="one per settled market day, in order")
    settlement_rule: str = Field(description="the rule every day was settled by, with every parameter")
    transport: dict[str, int | bool | dict[str, int]] = Field(description="the DMO's message counters")
    realised: dict[str, list[ReportedDay]] = Field(description=(
        "agent -> its realised days, in order; empty for an agent that reported none"))
    day: int | None = Field(None, description="of a one-day run: its day (1)")
    market_day: str = Field(description="the first market day")
    market_days: list[str] | None = Field(None, description="of a longer run: every market day")
    islanded_hours: list[int] | list[list[int]] = Field(description="a one-day run's; a longer one's, per day")
    clearing_prices: list[float] = Field(description="$/MWh, hour after hour, day after day")
    congestion: list[str]
    awards: dict[str, list[float]] = Field(description="agent -> MW, hour after hour, day after day")
    settlement: dict[str, AgentSettlement] = Field(description="agent -> its statements summed over the days")
    day_summary: SettledTotals | None = Field(None, description="of a one-day run")
    expected_cost: dict[str, float] | None = Field(None, description="of a one-day run")
    schedules_stopped_short: list[StoppedShort]
    rejected_messages: int
    rejected_by_code: dict[str, int]
    accepted_messages: dict[str, int]
    received_again: int
    dropped_messages: dict[str, int]
    locked_out: list[str]
    incidents: list[DatedIncident]
    phase_s: dict[str, float] | None = Field(None, description="of a one-day run")
