"""``dmosim solve``: one verified stochastic day-ahead schedule of one microgrid, as a table or JSON."""

from __future__ import annotations

import math

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import Instance, make_instance
from microgrid_agent.metrics import stochastic_metrics
from microgrid_agent.routes import resolve_method
from microgrid_agent.schedule import Schedule
from scenarios.case import load_case

from ..console import print_json, progress


def instance_from_args(args, **overrides) -> Instance:
    """The instance that the shared instance flags describe (``overrides`` replace single settings)."""
    settings = dict(
        scenarios=args.scenarios, subperiods=args.subperiods, seed=args.seed, sample_size=args.sample_size,
        cost_convention=args.cost_convention,
        island_hours=getattr(args, "island_hours", 1), transfer_scale=getattr(args, "transfer_scale", 1.0),
        penalty=getattr(args, "penalty", None),
    )
    return make_instance(load_case(args.case), **(settings | overrides))


def solve_verified(inst: Instance, args, label: str = "") -> Schedule:
    """Solve, then verify with the independent checker; a schedule that fails the check is a runtime failure."""
    s = inst.scen
    progress(f"{label}solving {inst.case.name} ({resolve_method(args.method, s.S)}): {s.S} scenarios x {s.N} sub-periods, "
             f"penalty {_money(inst.params.penalty)}/MWh, gap {args.gap:g}, time limit {args.time_limit:g} s")
    schedule = inst.solve(method=args.method, workers=args.workers, gap=args.gap, time_limit=args.time_limit,
                          verbose=getattr(args, "verbose", False), progress=lambda m: progress(label + m))
    report = check_schedule(inst.case, inst.scen, schedule, p_sch=inst.params.p_sch)
    if not report.ok:
        raise RuntimeError(report.summary(5))
    progress(f"{label}{schedule.status}: ${schedule.objective:,.2f}, gap {schedule.mip_gap:.3%}, "
             f"{schedule.timings.total_s:.1f} s; checker: all constraints hold in every scenario")
    return schedule


def run(args) -> int:
    inst = instance_from_args(args)
    schedule = solve_verified(inst, args)
    out = schedule.summary() | {"case": inst.case.name, "seed": args.seed, "verified": True}
    if args.metrics:
        progress(f"computing VSS and EVPI ({inst.scen.S + 2} more solves)")
        out["metrics"] = stochastic_metrics(inst, schedule, gap=args.gap, time_limit=args.time_limit).as_dict()
    if args.json:
        print_json(out)
    else:
        print(render(schedule, out))
    return 0


def _money(x: float) -> str:
    return "$inf" if math.isinf(x) else f"${x:,.0f}"


def render(schedule: Schedule, out: dict) -> str:
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
    if "metrics" in out:
        m = out["metrics"]
        rows.append(f"VSS             ${m['vss']:>12,.2f}   (EEV ${m['eev']:,.2f} - RP ${m['rp']:,.2f})")
        rows.append(f"EVPI            ${m['evpi']:>12,.2f}   (RP - WS ${m['ws']:,.2f})")
    return "\n".join(rows)
