"""The solver: every route of the stochastic schedule side by side in one run, over several scenario seeds.

For each scenario count and seed, the same instance (paper case, seeded scenarios) is solved by each route (Benders,
the decomposition in one SCIP tree when PySCIPOpt is installed, the extensive form) to the same target gap under the
same time cap; a route that hits the cap reports the gap it certified by then. Every schedule goes through the
independent checker. The summary is the median over the seeds: one scenario set's path through the masters is not
the route's speed (docs/solver.md, "The paper's day"). Each run's time is split into the branch-and-bound
tree (Benders' MILP masters, SCIP's tree, the extensive form's HiGHS solve), the scenario subproblems and building.
Beside the seconds, each run's work: simplex iterations and branch-and-bound nodes, in all, and for the decompositions
per master and per round of subproblems (``trace``), which are the same on every machine where the seconds are not.
Peak memory is the resident high-water mark of the process and of the subproblem workers.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import resource
import statistics
import time

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from microgrid_agent.solvers.benders import WORK
from microgrid_agent.solvers.extensive import SolveError
from microgrid_agent.solvers.routes import check_available
from scenarios.case import load_case

from ..arguments import gap, nonneg_float, positive_int
from ..console import UsageError, progress

TIMED_ROUTES = ("benders", "tree", "extensive")
SHARES = ("tree_share", "subproblems_share", "build_share")
TOTAL_WORK = ("simplex_iterations", "nodes")  # a solve's work in all, beside its seconds


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenarios", type=positive_int, nargs="+", default=[10, 20, 50, 100],
                        help="scenario counts to time (default: 10 20 50 100)")
    parser.add_argument("--routes", nargs="+", choices=TIMED_ROUTES, metavar="ROUTE",
                        help=f"routes to time, of {', '.join(TIMED_ROUTES)} (default: every one this installation "
                             "has; tree needs PySCIPOpt)")
    add_solve_flags(parser)
    parser.add_argument("--seed", type=int, default=0, help="the first scenario seed (default: 0)")
    parser.add_argument("--seeds", type=positive_int, default=3,
                        help="scenario seeds per count, from --seed on; the summary is their median (default: 3)")


def add_solve_flags(parser: argparse.ArgumentParser) -> None:
    """How each solve of a solver benchmark is set: sub-periods, gap, time cap, subproblem workers."""
    parser.add_argument("--subperiods", type=positive_int, default=6, help="metering sub-periods per hour (default: 6)")
    parser.add_argument("--gap", type=gap, default=0.005, help="relative MIP gap (default: 0.005)")
    parser.add_argument("--cap", type=nonneg_float, default=600.0,
                        help="time cap of each solve, seconds (default: 600)")
    parser.add_argument("--workers", type=positive_int, default=2,
                        help="processes for the scenario subproblems of the decomposed routes (default: 2)")


def routes_of(named: list[str] | None) -> list[str]:
    """The routes to time: those ``named`` (each must be installed), else every installed one."""
    if named is None:
        return [r for r in TIMED_ROUTES if r != "tree" or importlib.util.find_spec("pyscipopt") is not None]
    try:
        return [check_available(r) for r in dict.fromkeys(named)]
    except ValueError as exc:
        raise UsageError(f"--routes: {exc}") from None


def _peak_mib() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 1024


def _row(schedule, seconds: float, case, scen) -> dict:
    """One solve: its figures, whether the checker accepts it, and where its time went."""
    work = schedule.extra["work"]
    row = {"wall_s": seconds, "objective": schedule.objective, "bound": schedule.bound, "gap": schedule.mip_gap,
           "status": schedule.status, "verified": check_schedule(case, scen, schedule).ok,
           **{k: work[k] for k in TOTAL_WORK}}
    d = schedule.extra.get("decomposition")
    if d:
        row |= {"iterations": d["iterations"], "tree_share": d["master_s"] / seconds,
                "subproblems_share": d["subproblems_s"] / seconds, "build_share": d["build_s"] / seconds,
                **{k: d[k] for k in WORK}}
    else:
        row |= {"tree_share": schedule.timings.solve_s / seconds, "subproblems_share": 0.0,
                "build_share": schedule.timings.build_s / seconds}
    return row


def summary(rows: list[dict]) -> list[dict]:
    """Per scenario count and route, the median over the seeds that gave a schedule (with their range), and the
    median wall time over Benders' at the same count."""
    out = []
    for n in dict.fromkeys(r["scenarios"] for r in rows):
        for route in dict.fromkeys(r["route"] for r in rows):
            runs = [r for r in rows if r["scenarios"] == n and r["route"] == route]
            solved = [r for r in runs if "wall_s" in r]
            if not runs:
                continue
            line = {"scenarios": n, "route": route, "seeds": len(runs), "solved": len(solved)}
            if solved:
                walls = [r["wall_s"] for r in solved]
                line |= {"median_wall_s": statistics.median(walls), "min_wall_s": min(walls),
                         "max_wall_s": max(walls), "median_gap": statistics.median(r["gap"] for r in solved),
                         "verified": all(r["verified"] for r in solved)}
                if all("iterations" in r for r in solved):
                    line["median_iterations"] = statistics.median(r["iterations"] for r in solved)
                line |= {f"median_{k}": statistics.median(r[k] for r in solved) for k in (*TOTAL_WORK, *SHARES)}
            out.append(line)
    for line in out:
        benders = next((b for b in out if b["scenarios"] == line["scenarios"] and b["route"] == "benders"
                        and "median_wall_s" in b), None)
        if benders is not None and "median_wall_s" in line:
            line["over_benders"] = line["median_wall_s"] / benders["median_wall_s"]
    return out


def _load(routes: list[str]) -> None:
    """Import each route's solver code before any timing: the first solve of a route would carry it otherwise."""
    for route in routes:
        importlib.import_module(f"microgrid_agent.solvers.{route}")
    if "tree" in routes:
        importlib.import_module("pyscipopt")  # imported by the tree's solve itself, being optional


def run(args) -> dict:
    routes = routes_of(args.routes)
    _load(routes)
    case = load_case("paper")
    seeds = list(range(args.seed, args.seed + args.seeds))
    rows, steps = [], []
    for n in args.scenarios:
        for seed in seeds:
            inst = make_instance(case, scenarios=n, subperiods=args.subperiods, seed=seed)
            for route in routes:
                label = f"bench solver, {n} scenarios, seed {seed}"
                progress(f"{label}: {route}" + (f" (cap {args.cap:g} s)" if route == "extensive" else ""))
                start = time.perf_counter()
                try:
                    schedule = inst.solve(method=route, workers=args.workers, gap=args.gap, time_limit=args.cap,
                                          progress=lambda m, label=label: progress(f"{label}: {m}"))
                    row = _row(schedule, time.perf_counter() - start, case, inst.scen)
                    steps += _steps(schedule, {"scenarios": n, "seed": seed, "route": route})
                except SolveError as exc:
                    row = {"status": f"no schedule in {args.cap:g} s ({exc})"}
                rows.append({"scenarios": n, "seed": seed, "route": route, **row})
    return {"subperiods": args.subperiods, "target_gap": args.gap, "cap_s": args.cap, "seeds": seeds,
            "summary": summary(rows), "rows": rows, "trace": steps, "peak_rss_mib": _peak_mib()}


def _steps(schedule, run: dict) -> list[dict]:
    """A decomposed solve's trace, row by row (docs/solver.md, "What a solve reports"): each master's seconds,
    simplex iterations and nodes, and its round of subproblems' seconds and simplex iterations; none for the
    extensive form, whose one MILP is its row."""
    keys = ("phase", "master_s", "master_simplex_iterations", "master_nodes", "subproblems_s",
            "subproblems_simplex_iterations")
    return [run | {"step": i} | {k: r[k] for k in keys} for i, r in enumerate(schedule.extra.get("trace", []), 1)]
