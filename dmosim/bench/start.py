"""Each day's Benders schedule solved cold and started from the day before's first stage: the time a start saves.

A multi-day run hands each agent's solve the first stage of its previous schedule (microgrid_agent/agent/machine.py);
the Benders route evaluates it once its LP phase ends and, if the master's first-stage constraints allow it, takes
it as its first incumbent: an upper bound from the start, the first MILP master's cutoff and its MIP start
(``benders.begin_from``). Here consecutive days of the paper's microgrid (scenario seeds ``--seed``, ``--seed`` + 1,
...) are solved both ways to the same gap; day d is started from day d - 1's cold schedule, so that both ways of a
day see the same start. The two solves of a day run one after the other, in alternating order from day to day.
Every schedule goes through the independent checker.
"""

from __future__ import annotations

import argparse
import statistics
import time

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from scenarios.case import load_case

from ..arguments import positive_int
from ..console import progress
from .solver import add_solve_flags


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenarios", type=positive_int, default=20, help="scenarios per day (default: 20)")
    parser.add_argument("--days", type=positive_int, default=4,
                        help="consecutive days; the first has no day before (default: 4)")
    add_solve_flags(parser)
    parser.add_argument("--seed", type=int, default=0, help="the first day's scenario seed (default: 0)")


def run(args) -> dict:
    case = load_case("paper")
    rows, before = [], None
    for day in range(1, args.days + 1):
        inst = make_instance(case, scenarios=args.scenarios, subperiods=args.subperiods, seed=args.seed + day - 1)
        ways = ["cold"] if before is None else (["cold", "started"] if day % 2 else ["started", "cold"])
        solved = {}
        for way in ways:
            label = f"bench start, day {day} of {args.days}: {way}"
            progress(label)
            began = time.perf_counter()
            solved[way] = inst.solve(method="benders", workers=args.workers, gap=args.gap, time_limit=args.cap,
                                     start=before.first if way == "started" else None,
                                     progress=lambda m, label=label: progress(f"{label}: {m}"))
            solved[way + "_s"] = time.perf_counter() - began
        rows.append(day_row(day, solved, case, inst.scen))
        before = solved["cold"]
    started = [r for r in rows if "started_s" in r]
    return {"scenarios": args.scenarios, "subperiods": args.subperiods, "target_gap": args.gap, "cap_s": args.cap,
            "rows": rows, "summary": {
                "days started": len(started),
                "median started_s / cold_s": statistics.median(r["started_over_cold"] for r in started)
                if started else None,
                "seconds saved in all": sum(r["cold_s"] - r["started_s"] for r in started),
                "starts taken": sum(r["start_value"] is not None for r in started),
                "verified": all(r["verified"] for r in rows)}}


def day_row(day: int, solved: dict, case, scen) -> dict:
    """One day: each way's wall time, objective and iterations, the start's expected cost (None if the master
    set it aside), the ratio started / cold, and whether the checker accepts every schedule."""
    cold = solved["cold"]
    row = {"day": day, "cold_s": solved["cold_s"], "cold_objective": cold.objective,
           "cold_iterations": cold.extra["decomposition"]["iterations"]}
    schedules = [cold]
    if "started" in solved:
        started = solved["started"]
        start = next(r for r in started.extra["trace"] if r["phase"].startswith("start"))
        row |= {"started_s": solved["started_s"], "started_objective": started.objective,
                "started_iterations": started.extra["decomposition"]["iterations"],
                "start_value": start["upper_bound"] if start["phase"] == "start" else None,
                "started_over_cold": solved["started_s"] / solved["cold_s"]}
        schedules.append(started)
    row["verified"] = all(check_schedule(case, scen, s).ok for s in schedules)
    return row
