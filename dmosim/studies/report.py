"""What a study leaves: its tables as CSV, its figure and a text summary of its results."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
from matplotlib.figure import Figure

from . import figures
from .paper import Frames, table2_agreement


def write_csv(frame: pd.DataFrame, path: Path) -> Path:
    """A study's table as CSV that loads straight into pandas (the index only where it carries something)."""
    plain = isinstance(frame.index, pd.RangeIndex) and frame.index.name is None  # row numbers carry nothing
    frame.to_csv(path, index=not plain, float_format="%.10g")  # pandas writes an infinite penalty as "inf"
    return path


def figure(name: str, frames: Frames, convention: str, k: int, units: list[str]) -> Figure:
    """The study's figure: Table II as heat maps, or the cost curve or dispatch of Figs. 2-5."""
    if name == "table2":
        return figures.table2_figure(frames, table2_agreement(frames))
    if name == "islanding":
        return figures.islanding_figure(frames["islanding"], convention, k)
    if name == "transfer":
        return figures.transfer_figure(frames["transfer"], frames["transfer_paper"], convention, k)
    if name == "dispatch":
        return figures.dispatch_figure(frames["dispatch"], units)
    return figures.penalty_figure(frames["penalty"], convention, k)


def render(name: str, frames: Frames, convention: str, k: int, units: list[str]) -> str:
    """The text summary: the commitment grid for Table II, unit energies for Fig. 4, a cost table otherwise."""
    if name == "table2":
        return _render_table2(frames)
    if name == "dispatch":
        return _render_dispatch(frames["dispatch"], units)
    frame = frames[name]
    key = frame.columns[0]
    rows = [f"{key:>15} {'total $':>12} {'generation':>12} {'start-up':>10} {'curtailment':>12} {'penalty':>10} "
            f"{'gap':>7} {'solve s':>8}"]
    paid = figures.component(frame, "penalty")
    for _, r in frame.iterrows():
        shown = ("inf" if math.isinf(r[key]) else f"{r[key]:g}") + (f" {r['award']}" if "award" in frame else "")
        rows.append(f"{shown:>15} {r['objective']:>12,.0f} {r['generation']:>12,.0f} {r['startup']:>10,.0f} "
                    f"{r['curtailment']:>12,.0f} {r[paid]:>10,.0f} {r['mip_gap']:>7.2%} {r['solve_s']:>8.1f}")
    rows.append(f"(costs in the {convention} convention at {k} sub-periods/h)")
    if name == "transfer":
        p = frames["transfer_paper"]
        rows.append("paper, converted: " + ", ".join(f"{s:g}x ${v:,.0f}" for s, v in
                                                    zip(p["transfer_scale"], p["objective_converted"])))
    return "\n".join(rows)


def _render_table2(frames: Frames) -> str:
    ours, paper = frames["table2"], frames["table2_paper"]
    hours = list(range(1, 25))
    rows = [f"{'hour':<17}" + "".join(f"{h:>3}" for h in hours)]
    for case, table, marks in (("ours", ours.loc["island_1h"], ours.loc["changed"]),
                               ("paper", paper.loc["paper"], paper.loc["paper_bold"])):
        for unit in paper.loc["paper"].index:
            cells = "".join(f"{v:>2}{'*' if m else ' '}" for v, m in zip(table.loc[unit, hours], marks.loc[unit, hours]))
            rows.append(f"{case + ' ' + unit:<16} {cells}")
    a = table2_agreement(frames)
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
