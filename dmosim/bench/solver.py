"""The solver: Benders decomposition against the extensive form in plain HiGHS, side by side in one run.

For each scenario count, the same instance (paper case, seeded scenarios) is solved by both routes to the same
target gap; the extensive form gets a time cap, and whatever gap it has certified by then is reported. Both
schedules go through the independent checker. Peak memory is the resident high-water mark of the process
(the Benders subproblem workers report their own).
"""

from __future__ import annotations

import argparse
import resource
import time

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from microgrid_agent.solvers.benders import solve_decomposed
from microgrid_agent.solvers.extensive import SolveError
from scenarios.case import load_case

from ..arguments import gap, nonneg_float, positive_int
from ..console import progress


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenarios", type=positive_int, nargs="+", default=[10, 20, 50, 100],
                        help="scenario counts to time (default: 10 20 50 100)")
    parser.add_argument("--subperiods", type=positive_int, default=6, help="metering sub-periods per hour (default: 6)")
    parser.add_argument("--gap", type=gap, default=0.005, help="relative MIP gap (default: 0.005)")
    parser.add_argument("--cap", type=nonneg_float, default=600.0, help="time cap of each solve, seconds")
    parser.add_argument("--workers", type=positive_int, default=2,
                        help="processes for the Benders subproblems (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scenarios (default: 0)")
    parser.add_argument("--skip-extensive", action="store_true", help="time the decomposition only")


def _peak_mib() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024


def _row(route: str, schedule, seconds: float, case, scen) -> dict:
    ok = check_schedule(case, scen, schedule).ok
    row = {"route": route, "wall_s": seconds, "objective": schedule.objective, "bound": schedule.bound,
           "gap": schedule.mip_gap, "status": schedule.status, "verified": ok}
    d = schedule.extra.get("decomposition")
    if d:
        row |= {"iterations": d["iterations"], "s_per_iteration": seconds / max(d["iterations"], 1),
                "subproblems_share": d["subproblems_s"] / seconds, "master_share": d["master_s"] / seconds,
                "build_share": d["build_s"] / seconds}
    return row


def run(args) -> dict:
    case = load_case("paper")
    rows = []
    for n in args.scenarios:
        inst = make_instance(case, scenarios=n, subperiods=args.subperiods, seed=args.seed)
        label = f"bench solver, {n} scenarios: "
        progress(f"{label}benders")
        start = time.perf_counter()
        try:
            benders = solve_decomposed(case, inst.scen, inst.params, gap=args.gap, time_limit=args.cap,
                                       workers=args.workers, progress=lambda m: progress(label + m))
            rows.append({"scenarios": n, **_row("benders", benders, time.perf_counter() - start, case, inst.scen)})
        except SolveError as exc:
            rows.append({"scenarios": n, "route": "benders", "status": f"failed: {exc}"})
        if args.skip_extensive:
            continue
        progress(f"{label}extensive form (cap {args.cap:g} s)")
        start = time.perf_counter()
        try:
            extensive = inst.solve(gap=args.gap, time_limit=args.cap)
            rows.append({"scenarios": n, **_row("extensive", extensive, time.perf_counter() - start, case, inst.scen)})
        except SolveError as exc:
            rows.append({"scenarios": n, "route": "extensive", "status": f"no incumbent in {args.cap:g} s ({exc})"})
    ratios = []
    for n in args.scenarios:
        pair = {r["route"]: r for r in rows if r["scenarios"] == n and "wall_s" in r}
        if len(pair) == 2:
            ratios.append({"scenarios": n, "extensive_over_benders_wall": pair["extensive"]["wall_s"] / pair["benders"]["wall_s"],
                           "extensive_gap": pair["extensive"]["gap"], "benders_gap": pair["benders"]["gap"]})
    return {"subperiods": args.subperiods, "target_gap": args.gap, "cap_s": args.cap, "rows": rows,
            "ratios": ratios, "peak_rss_mib": _peak_mib()}
