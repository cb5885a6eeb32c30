"""Synthetic results of runs for the tests of their readers: a partial result (a dict of what a test cares about)
made a whole, typed one."""

from __future__ import annotations

from dmo.operator.report import AgentSettlement, ReportedDay
from dmosim.results.report import RunReport


def typed(res: dict) -> RunReport:
    """A synthetic result as the run's typed result: what it does not say is empty, zero or ok."""
    money = dict.fromkeys(AgentSettlement.model_fields, 0.0) | {"missing_subperiods": 0}
    totals = {**money, "agents": [], "agents_without_meter": []}
    del totals["award_mwh"], totals["import_mwh"]
    figures = {"islanded_hours": [], "clearing_prices": [], "congestion": [], "awards": {}, "settlement": {},
               "expected_cost": {}, "schedules_stopped_short": [], "rejected_messages": 0, "rejected_by_code": {},
               "accepted_messages": {}, "received_again": 0, "dropped_messages": {}, "locked_out": [],
               "incidents": [], "phase_s": {}}
    days = [{**figures, "day": n, "day_summary": totals, **d,
             "settlement": {a: money | st for a, st in d.get("settlement", {}).items()}}
            for n, d in enumerate(res.get("days", []), 1)]
    run = {**figures, "run_id": "r", "agents": [], "settlement_rule": "paper", "transport": {}, "realised": {},
           "market_day": "2026-07-01", "experiment": "run", "wall_s": 0.0, "run_dir": "r", "logs": "r/logs",
           "recording": None, "faults": [], "restarts": {}, "verdict": {"ok": True, "problems": []}}
    return RunReport.model_validate({**run, **res, "days": days,
                                     "settlement": {a: money | st for a, st in res.get("settlement", {}).items()}})


def realised_day(day: int, compute: list[dict], messages: dict) -> ReportedDay:
    """An agent's realised day of the run's result with ``compute`` entries and ``messages`` counts, the rest zero."""
    return ReportedDay.model_validate({
        "day": day, "market_day": f"2026-07-0{day}", "generation": 0.0, "startup": 0.0, "curtailment": 0.0,
        "penalty": 0.0, "total": 0.0, "curtailment_mwh": 0.0, "deviation_mwh": 0.0, "units": {}, "stored_mwh": None,
        "compute": compute, "messages": messages})
