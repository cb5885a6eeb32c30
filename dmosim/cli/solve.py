"""``dmosim solve``: one verified stochastic day-ahead schedule of one microgrid, as a table or JSON.

Like every verb module it holds its flags (``add_arguments``) and its body (``run``); the solver stack is
imported only when a solve runs, so that the command line starts in about a second.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import TYPE_CHECKING

from dmo.market.rules import MAX_RATE
from messages.schemas import MAX_SUBPERIODS
from microgrid_agent.solvers.routes import METHODS, auto_rule, check_available
from scenarios.case import load_case
from scenarios.days import MAX_SEED
from scenarios.fleet import MAX_SCALE
from scenarios.generation import MAX_SAMPLE, MAX_SCENARIOS

from ..arguments import gap, hours, integer, number, seconds, seed
from ..console import UsageError, print_json, progress
from ..experiment.spec import MAX_WORKERS

if TYPE_CHECKING:
    from microgrid_agent.instance import Instance
    from microgrid_agent.schedule import StochasticSchedule

HELP = "one stochastic day-ahead schedule of one microgrid"
# Each replication is a whole solve of its own (135 s at 20 scenarios, docs/solver.md): 100 is 20 times the 5 the
# docs use, about four hours at that size.
MAX_REPLICATIONS = 100
# Seconds of the paper's day (100 scenarios, 144 sub-periods, seed 0) on the 2-core Intel Xeon of docs/solver.md,
# "The paper's day", measured beside other work. A solve's default time limit is at least HEADROOM times it, so that a
# machine three times slower, or three times as loaded, still certifies the paper's size ("Time limits" there).
PAPER_DAY_S = 312.3
HEADROOM = 3.0
TIME_LIMIT_S = 1800.0


def add_instance_flags(p: argparse.ArgumentParser, scenarios: int) -> None:
    """The flags that define one scheduling instance, shared by ``solve`` and ``study``."""
    p.add_argument("--case", default="paper", help="built-in case name or path to a case TOML file (default: paper)")
    p.add_argument("--scenarios", type=integer(1, MAX_SCENARIOS), default=scenarios,
                   help=f"scenarios after reduction, at most {MAX_SCENARIOS} (default: {scenarios})")
    p.add_argument("--sample-size", type=integer(1, MAX_SAMPLE), default=None,
                   help=f"scenarios sampled before reduction, --scenarios..{MAX_SAMPLE} (default: 10x)")
    p.add_argument("--subperiods", type=integer(1, MAX_SUBPERIODS), default=6,
                   help=f"sub-periods per hour, at most {MAX_SUBPERIODS} (default: 6, i.e. 10 minutes)")
    p.add_argument("--seed", type=seed, default=0, help=f"seed of the scenario draws, 0..{MAX_SEED} (default: 0)")
    p.add_argument("--islanding", choices=("random", "stratified"), default="random",
                   help="how islanding start hours are drawn: random (each uniform over the day) or stratified "
                        "(spread evenly over the day, each start hour weighted by its probability); default: random")
    p.add_argument("--gap", type=gap, default=0.005, help="relative MIP gap to reach (default: 0.005)")
    p.add_argument("--time-limit", type=seconds, default=TIME_LIMIT_S,
                   help=f"seconds per solve (default: {TIME_LIMIT_S:g}, docs/solver.md \"Time limits\")")
    p.add_argument("--cost-convention", choices=("real", "paper"), default="real",
                   help="real: energy costs x dt; paper: objective (1) as printed, no dt (see docs/model.md)")
    p.add_argument("--take-award", action="store_true",
                   help="the award must be taken while connected (P_M = P_sch; what cannot be absorbed is priced at "
                        "VOLL), not only kept below (docs/model.md, \"How the award binds\"); the transfer study "
                        "solves both readings")
    add_method_flags(p, workers=2)


def add_method_flags(p: argparse.ArgumentParser, workers: int) -> None:
    """How the stochastic schedule is solved."""
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="extensive: one MILP in HiGHS (the reference); benders: multi-cut decomposition "
                        "(docs/solver.md); tree: the decomposition in one SCIP branch-and-bound tree (pip install "
                        f"'dmosim[scip]'); auto (default): {auto_rule()}")
    p.add_argument("--workers", type=integer(1, MAX_WORKERS), default=workers,
                   help=f"processes for the Benders subproblems, at most {MAX_WORKERS} (default: {workers})")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_instance_flags(p, scenarios=10)
    p.add_argument("--island-hours", type=hours, default=1, help="islanding hours per scenario (default: 1)")
    p.add_argument("--transfer-scale", type=number(0, MAX_SCALE), default=1.0,
                   help=f"multiplier of the award P_sch, 0..{MAX_SCALE:g} (default: 1)")
    p.add_argument("--penalty", type=number(0, MAX_RATE, allow_inf=True), default=None,
                   help="$/MWh above the award, or inf (default: the case's)")
    p.add_argument("--metrics", action="store_true", help="also compute VSS and EVPI (solves S + 2 more problems)")
    p.add_argument("--evaluate", type=integer(2, MAX_SAMPLE), metavar="N", default=None,
                   help="also evaluate the schedule's first stage on N fresh scenarios (LPs only): its expected "
                        "cost for the uncertainty it was drawn from, with a 95%% confidence interval "
                        f"(docs/solver.md, \"Out of sample\"); N in 2..{MAX_SAMPLE}")
    p.add_argument("--replications", type=integer(2, MAX_REPLICATIONS), metavar="R", default=None,
                   help="also solve R independent sample problems of --scenarios scenarios each (sampled, not "
                        "reduced): a statistical lower bound of the true optimum, and with --evaluate the "
                        "schedule's optimality gap with a 95%% upper limit (docs/solver.md, \"Out of sample\"); R "
                        f"in 2..{MAX_REPLICATIONS}")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (docs/solver.md, \"What a solve reports\")")
    p.add_argument("--verbose", action="store_true", help="show the HiGHS log")


def check_instance_flags(args) -> None:
    """What the instance flags' types cannot see alone: a sample of at least the scenarios it is reduced to, and a
    method this installation has."""
    try:
        check_available(args.method)
    except ValueError as exc:
        raise UsageError(f"--method {exc}") from None
    if args.sample_size is not None and args.sample_size < args.scenarios:
        raise UsageError(f"--sample-size {args.sample_size}: the sample is reduced to --scenarios {args.scenarios}, "
                         "so it needs at least as many")


def instance_from_args(args, **overrides) -> Instance:
    """The instance that the shared instance flags describe (``overrides`` replace single settings)."""
    from microgrid_agent.instance import make_instance  # noqa: PLC0415  (the solver stack: seconds to import)

    settings = dict(
        scenarios=args.scenarios, subperiods=args.subperiods, seed=args.seed, sample_size=args.sample_size,
        cost_convention=args.cost_convention, take_award=args.take_award, stratified=args.islanding == "stratified",
        island_hours=getattr(args, "island_hours", 1), transfer_scale=getattr(args, "transfer_scale", 1.0),
        penalty=getattr(args, "penalty", None),
    )
    return make_instance(load_case(args.case), **(settings | overrides))


def solve_verified(inst: Instance, args, label: str = "") -> StochasticSchedule:
    """Solve, then verify with the independent checker; a schedule that fails the check is a runtime failure."""
    from microgrid_agent.checker import check_schedule  # noqa: PLC0415
    from microgrid_agent.solvers.routes import resolve_method  # noqa: PLC0415

    s = inst.scen
    route = resolve_method(args.method, s.S, s.subperiods)
    progress(f"{label}solving {inst.case.name} ({route}): {s.S} scenarios x {s.N} sub-periods, "
             f"penalty {_money(inst.params.penalty)}/MWh{', award must be taken' if inst.params.take_award else ''}, "
             f"gap {args.gap:g}, time limit {args.time_limit:g} s")
    schedule = inst.solve(method=args.method, workers=args.workers, gap=args.gap, time_limit=args.time_limit,
                          verbose=getattr(args, "verbose", False), progress=lambda m: progress(label + m))
    report = check_schedule(inst.case, inst.scen, schedule, p_sch=inst.params.p_sch)
    if not report.ok:
        raise RuntimeError(report.summary(5))
    progress(f"{label}{schedule.status}: ${schedule.objective:,.2f}, gap {schedule.mip_gap:.3%}, "
             f"{schedule.timings.total_s:.1f} s; checker: all constraints hold in every scenario")
    return schedule


def run(args) -> int:
    check_instance_flags(args)
    inst = instance_from_args(args)
    schedule = solve_verified(inst, args)
    out = schedule.summary() | {"case": inst.case.name, "seed": args.seed, "verified": True}
    if args.metrics:
        from microgrid_agent.metrics import stochastic_metrics  # noqa: PLC0415

        progress(f"computing VSS and EVPI ({inst.scen.S + 2} more solves)")
        out["metrics"] = stochastic_metrics(inst, schedule, gap=args.gap, time_limit=args.time_limit).as_dict()
    if args.evaluate is not None:
        out["evaluation"] = evaluate(inst, schedule, args)
    if args.replications is not None:
        out |= replicate(args, out.get("evaluation"))
    if args.json:
        print_json(out)
    else:
        print(render(schedule, out))
    return 0


def evaluate(inst: Instance, schedule: StochasticSchedule, args) -> dict:
    """``--evaluate N``: the schedule's first stage on N fresh scenarios, drawn as the instance's from another
    seed, with the same islanding hours."""
    from microgrid_agent.solvers.evaluation import evaluate_schedule, fresh_seed  # noqa: PLC0415
    from scenarios.generation import sample  # noqa: PLC0415

    progress(f"evaluating the first stage on {args.evaluate} fresh scenarios")
    stratified = args.islanding == "stratified"
    fresh = sample(inst.case, args.evaluate, inst.scen.subperiods, island_hours=getattr(args, "island_hours", 1),
                   seed=fresh_seed(args.seed), stratified=stratified)
    result = evaluate_schedule(inst.case, schedule, inst.params, fresh, workers=args.workers,
                               stratified=stratified).as_dict()
    progress(f"out of sample: ${result['expected_cost']:,.2f}, 95% interval ${result['low']:,.2f} .. "
             f"${result['high']:,.2f} ({result['seconds']:.1f} s)")
    return result


def replicate(args, evaluation: dict | None) -> dict:
    """``--replications R``: R sample problems of ``--scenarios`` i.i.d. scenarios (no reduction, so that each is
    an unbiased sample problem), each solved and verified; their bounds give the statistical lower bound, and with
    an evaluation the optimality gap."""
    from microgrid_agent.solvers.evaluation import (Evaluation, lower_bound, optimality_gap,  # noqa: PLC0415
                                                    replication_seed)

    start, bounds = time.perf_counter(), []
    for r in range(args.replications):
        inst = instance_from_args(args, seed=replication_seed(args.seed, r), sample_size=args.scenarios)
        bounds.append(solve_verified(inst, args, f"[replication {r + 1}/{args.replications}] ").bound)
    lower = lower_bound(bounds, args.scenarios, time.perf_counter() - start)
    progress(f"statistical lower bound: ${lower.estimate:,.2f}, 95% lower limit ${lower.low:,.2f} "
             f"({lower.replications} replications, {lower.seconds:.1f} s)")
    out = {"replications": lower.as_dict()}
    if evaluation is not None:
        out["optimality_gap"] = optimality_gap(Evaluation(**evaluation), lower)
    return out


def _money(x: float) -> str:
    return "$inf" if math.isinf(x) else f"${x:,.0f}"


def render(schedule: StochasticSchedule, out: dict) -> str:
    """A terminal report: hourly first-stage decisions, then costs, bound and timings."""
    hours = "".join(f"{t:>3}" for t in range(1, 25))
    rows = [f"{'hour':<12}{hours}"]
    for frame in (schedule.commitment, schedule.storage_mode, schedule.load_state):
        for name in frame.columns:
            rows.append(f"{name:<12}" + "".join(f"{v:>3}" for v in frame[name]))
        rows.append("")
    c = schedule.cost
    rows += [
        f"expected cost   ${schedule.objective:>12,.2f}   ({schedule.cost_convention} convention)",
        f"  generation    ${c.generation:>12,.2f}",
        f"  start-up      ${c.startup:>12,.2f}",
        f"  curtailment   ${c.curtailment:>12,.2f}",
        f"  penalty       ${c.penalty:>12,.2f}",
        f"bound           ${schedule.bound:>12,.2f}   gap {schedule.mip_gap:.3%}   status {schedule.status}",
        f"time            build {schedule.timings.build_s:.2f} s, solve {schedule.timings.solve_s:.2f} s, "
        f"total {schedule.timings.total_s:.2f} s",
    ]
    if "evaluation" in out:
        e = out["evaluation"]
        rows.append(f"out of sample   ${e['expected_cost']:>12,.2f}   95% interval ${e['low']:,.2f} .. ${e['high']:,.2f} "
                    f"({e['scenarios']} fresh scenarios, first stage fixed; in sample ${schedule.objective:,.2f})")
    if "replications" in out:
        b = out["replications"]
        rows.append(f"lower bound     ${b['estimate']:>12,.2f}   95% lower limit ${b['low']:,.2f} ({b['replications']} "
                    f"replications of {b['scenarios']} sampled scenarios: a statistical bound of the true optimum)")
    if "optimality_gap" in out:
        g = out["optimality_gap"]
        rows.append(f"optimality gap  ${g['estimate']:>12,.2f}   95% upper limit ${g['high']:,.2f} "
                    f"({g['relative_high']:.2%} of the out-of-sample cost)")
    if "metrics" in out:
        m = out["metrics"]
        rows.append(f"VSS             ${m['vss']:>12,.2f}   (EEV ${m['eev']:,.2f} - RP ${m['rp']:,.2f})")
        rows.append(f"EVPI            ${m['evpi']:>12,.2f}   (RP - WS ${m['ws']:,.2f})")
    return "\n".join(rows)
