"""A week of market days as processes: wall time and protocol overhead per day, each role's memory on the first
and the last day, and the recording's size per agent-day.

One ``dmosim run --days D --agents N --json`` of small agents. Per day, the DMO's phase times and the agents'
``compute`` entries of that day split the day into the agents' critical-path computation and overhead
(``dmosim.bench.day.split_day``); the run samples each role's resident, peak and proportional memory as each day's
last hour starts (``memory_mib`` of the result). What must not grow with the days is checked as ratios of the last
day to the first.
"""

from __future__ import annotations

import argparse
import os

from ..arguments import nonneg_float
from ..results.report import RunReport
from .day import add_run_flags, run_and_read, run_flags, split_day


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_flags(parser, agents=10, days=7, scenarios=1, subperiods=1, gap_=0.05)
    parser.add_argument("--time-limit", type=nonneg_float, default=120.0, help="seconds per agent solve (default: 120)")
    parser.add_argument("--timeout", type=nonneg_float, default=7200.0,
                        help="seconds the whole run may take before the bench stops it (default: 7200)")


def run(args) -> dict:
    cores = os.cpu_count() or 1
    run = run_and_read([*run_flags(args), "--time-limit", repr(args.time_limit)], args.timeout)
    result, compute = run["result"], run["compute"]
    report = summarise(result, compute, cores)
    report["setup"] = {"agents": args.agents, "days": args.days, "scenarios": args.scenarios,
                       "subperiods": args.subperiods, "gap": args.gap, "hosting": args.hosting,
                       "per_process": args.per_process, "recording": "on",
                       "process_s": round(run["process_s"], 1),
                       "machine": f"{cores} cores shared with other work: one run, noisy"}
    return {"setup": report.pop("setup"), **report}


def summarise(result: RunReport, compute: dict[str, list[dict]], cores: int) -> dict:
    """Per day the split of ``split_day``; per role its memory on the first and the last day; the ratios."""
    days = []
    for day in result.days:
        own = {agent: [e for e in entries if e.get("day", 1) == day.day] for agent, entries in compute.items()}
        totals = split_day(day.phase_s, own, cores)["totals"]
        days.append({"day": day.day, "market_day": day.market_day, "day_s": round(totals["day_s"], 2),
                     "compute_s": round(totals["compute_s"], 2), "overhead_pct": round(totals["overhead_pct"], 2),
                     "per_hour_ms": round(totals["per_hour_ms"], 1), "incidents": len(day.incidents)})
    memory = {day: {role: m.model_dump() for role, m in roles.items()} for day, roles in (result.memory_mib or {}).items()}
    by_day = [memory.get(str(d["day"]), {}) for d in days]
    roles = [role_memory(name, [m.get(name, {}) for m in by_day])
             for name in sorted(set(by_day[0]) & set(by_day[-1]))]
    recorded = result.recorded
    agent_days = len(result.agents) * len(days)
    return {
        "days": days,
        "memory": roles,
        "ratios": {
            "last_day_s / first_day_s": round(days[-1]["day_s"] / days[0]["day_s"], 3),
            "mean overhead_pct": round(sum(d["overhead_pct"] for d in days) / len(days), 2),
            "max rss_mib last / first day (any role)": max((r["rss_ratio"] for r in roles), default=None),
            "max rss_mib last / second day (any role)": max((r["rss_ratio_from_day_2"] for r in roles
                                                              if "rss_ratio_from_day_2" in r), default=None),
            "max peak_mib last / first day (any role)": max((r["peak_ratio"] for r in roles), default=None),
            "recording bytes per agent-day": round(((recorded and recorded.bytes) or 0) / agent_days) if agent_days
            else None,
        },
    }


def role_memory(name: str, days: list[dict]) -> dict:
    """One role's memory over the days (``memory_mib`` of each): its resident, peak and, where the kernel gives it,
    proportional memory on the first and the last day, each with its ratio last / first; its resident memory on
    every day (``rss_by_day_mib``, None where not sampled), and the ratio of the last day's to the second's
    (``rss_ratio_from_day_2``): the first day's sample comes before any settlement, so a role that only fills its
    allocator's working set over the first days and then holds it shows there, and one that grows with the days
    shows in both."""
    first, last = days[0], days[-1]
    row = {"role": name}
    for what in ("rss", "peak", "pss"):
        a, b = first.get(f"{what}_mib"), last.get(f"{what}_mib")
        if a is not None and b is not None:
            row |= {f"{what}_first_mib": a, f"{what}_last_mib": b, f"{what}_ratio": round(b / a, 3)}
    row["rss_by_day_mib"] = [d.get("rss_mib") for d in days]
    second = days[1].get("rss_mib") if len(days) > 2 else None
    if second and last.get("rss_mib") is not None:
        row["rss_ratio_from_day_2"] = round(last["rss_mib"] / second, 3)
    return row
