"""``dmosim study NAME``: runs one of the paper's studies with verified solves, writes its CSV and PNG files under
--out, and prints a short table of the results."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from microgrid_agent import studies
from scenarios.case import load_case

from .. import plots
from ..console import UsageError
from .solve import instance_from_args, progress, solve_verified


def output_dir(text: str) -> Path:
    """--out as a directory, created if missing; anything else there is a usage error (before any solve)."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {text}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {text}: cannot create the directory ({exc.strerror})") from None
    return out


def run(args) -> int:
    out = output_dir(args.out)
    study = studies.STUDIES[args.name]
    progress(f"study {args.name}: {args.scenarios} scenarios x {args.subperiods} sub-periods/h, seed {args.seed}, "
             f"{args.cost_convention} cost convention -> {out}/")
    frames = study(lambda **overrides: instance_from_args(args, **overrides),
                   lambda inst, label: solve_verified(inst, args, label))
    written = [_write_csv(frame, out / f"{name}.csv") for name, frame in frames.items()]
    written.append(plots.save(_figure(args, frames), out / f"{args.name}.png"))
    print(render(args, frames))
    print("\nfiles written:")
    for path in written:
        print(f"  {path}")
    return 0


def _write_csv(frame: pd.DataFrame, path: Path) -> Path:
    plain = isinstance(frame.index, pd.RangeIndex) and frame.index.name is None  # row numbers carry nothing
    frame.to_csv(path, index=not plain, float_format="%.10g")  # pandas writes an infinite penalty as "inf"
    return path


def _figure(args, frames: dict[str, pd.DataFrame]):
    k, convention = args.subperiods, args.cost_convention
    if args.name == "table2":
        return plots.table2_figure(frames, studies.table2_agreement(frames))
    if args.name == "islanding":
        return plots.islanding_figure(frames["islanding"], convention, k)
    if args.name == "transfer":
        return plots.transfer_figure(frames["transfer"], frames["transfer_paper"], convention, k)
    if args.name == "dispatch":
        return plots.dispatch_figure(frames["dispatch"], [u.name for u in load_case(args.case).units])
    return plots.penalty_figure(frames["penalty"], convention, k)


def render(args, frames: dict[str, pd.DataFrame]) -> str:
    """The stdout summary: the commitment grid for Table II, unit energies for Fig. 4, a cost table otherwise."""
    if args.name == "table2":
        return _render_table2(frames)
    if args.name == "dispatch":
        return _render_dispatch(frames["dispatch"], [u.name for u in load_case(args.case).units])
    frame = frames[args.name]
    key = frame.columns[0]
    rows = [f"{key:>15} {'total $':>12} {'generation':>12} {'start-up':>10} {'curtailment':>12} {'penalty':>10} "
            f"{'gap':>7} {'solve s':>8}"]
    paid = plots.component(frame, "penalty")
    for _, r in frame.iterrows():
        shown = "inf" if math.isinf(r[key]) else f"{r[key]:g}"
        rows.append(f"{shown:>15} {r['objective']:>12,.0f} {r['generation']:>12,.0f} {r['startup']:>10,.0f} "
                    f"{r['curtailment']:>12,.0f} {r[paid]:>10,.0f} {r['mip_gap']:>7.2%} {r['solve_s']:>8.1f}")
    rows.append(f"(costs in the {args.cost_convention} convention at {args.subperiods} sub-periods/h)")
    if args.name == "transfer":
        p = frames["transfer_paper"]
        rows.append("paper, converted: " + ", ".join(f"{s:g}x ${v:,.0f}" for s, v in
                                                    zip(p["transfer_scale"], p["objective_converted"])))
    return "\n".join(rows)


def _render_table2(frames: dict[str, pd.DataFrame]) -> str:
    ours, paper = frames["table2"], frames["table2_paper"]
    hours = list(range(1, 25))
    rows = [f"{'hour':<17}" + "".join(f"{h:>3}" for h in hours)]
    for case, table, marks in (("ours", ours.loc["island_1h"], ours.loc["changed"]),
                               ("paper", paper.loc["paper"], paper.loc["paper_bold"])):
        for unit in paper.loc["paper"].index:
            cells = "".join(f"{v:>2}{'*' if m else ' '}" for v, m in zip(table.loc[unit, hours], marks.loc[unit, hours]))
            rows.append(f"{case + ' ' + unit:<16} {cells}")
    a = studies.table2_agreement(frames)
    rows.append("* = differs from the case without islanding (ours) / printed bold (paper)")
    rows.append(f"agreement with the paper: {a['equal']} of {a['of']} unit-hours; "
                f"change marks equal in {a['changed_equal']} of {a['of']}")
    return "\n".join(rows)


def _render_dispatch(frame: pd.DataFrame, units: list[str]) -> str:
    k = int(frame.index.get_level_values("subperiod").max())
    islanded = frame["connected"] < 0.5
    hours = sorted(set(frame.index.get_level_values("hour")[islanded]))
    rows = [f"islanded hours: {', '.join(map(str, hours)) or 'none'}",
            f"{'':<12}{'day MWh':>10}{'islanded MWh':>14}{'peak MW':>9}"]
    for name in [*units, "p_m", "storage", "load_shed"]:
        rows.append(f"{name:<12}{frame[name].sum() / k:>10.2f}{frame.loc[islanded, name].sum() / k:>14.2f}"
                    f"{frame[name].max():>9.2f}")
    return "\n".join(rows)
