"""The figures of ``dmosim study``: one function per figure, each from a study's DataFrames to a matplotlib Figure."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from dmosim.results.style import figure

COMPONENTS = ("generation", "startup", "curtailment", "penalty")
_ON_OFF = ListedColormap(["white", "#4c72b0"])


def cost_label(cost_convention: str, subperiods: int) -> str:
    """The y-axis label of a cost: real dollars, or the paper's convention (objective (1) without dt)."""
    if cost_convention == "paper":
        return f"expected cost, paper convention\n($, no Δt at {subperiods} sub-periods/h)"
    return "expected daily cost ($)"


def component(frame: pd.DataFrame, name: str) -> str:
    """The column of cost term ``name``: "penalty_cost" in the penalty study, where "penalty" is the rate c."""
    return f"{name}_cost" if f"{name}_cost" in frame else name


def save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=120, bbox_inches="tight")
    return path


def _thousands(ax) -> None:
    ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda y, _: f"{y:,.0f}"))


def _cost_lines(ax, x, frame: pd.DataFrame) -> None:
    """Total and each nonzero component against x; the total's gap as an error bar down to the bound."""
    ax.errorbar(x, frame["objective"], yerr=[frame["objective"] - frame["bound"], 0 * frame["bound"]],
                fmt="o-", color="black", lw=2, capsize=3, label="total (bar: down to MIP bound)")
    for name, style in zip(COMPONENTS, ("s--", "^--", "v--", "d--")):
        column = component(frame, name)
        if (frame[column].abs() > 1e-9).any():
            ax.plot(x, frame[column], style, label=name)
    ax.grid(alpha=0.3)
    _thousands(ax)


def table2_figure(frames: dict[str, pd.DataFrame], agreement: dict[str, int]) -> Figure:
    """Table II as heat maps: our 1-hour-islanding commitment (changes vs no islanding outlined), the paper's
    (bold entries outlined), and where the two disagree."""
    ours, paper = frames["table2"], frames["table2_paper"]
    hours = list(range(1, 25))
    units = list(paper.loc["paper"].index)
    panels = [
        ("ours: 1-hour islanding (outlined: differs from our no-islanding commitment)",
         ours.loc["island_1h"].loc[units, hours], ours.loc["changed"].loc[units, hours]),
        ("paper, Table II (outlined: printed bold; G4 padded at hours 23-24, see table2_paper.csv)",
         paper.loc["paper"][hours], paper.loc["paper_bold"][hours]),
    ]
    fig = figure(figsize=(11, 6.8), constrained_layout=True)
    axes = fig.subplots(3, 1)
    for ax, (title, on, marked) in zip(axes, panels):
        _grid(ax, on.to_numpy(), marked.to_numpy(), units, title)
    diff = (panels[0][1].to_numpy() != panels[1][1].to_numpy()).astype(int)
    _grid(axes[2], diff, np.zeros_like(diff), units,
          f"disagreement (filled: ours ≠ paper): equal in {agreement['equal']} of {agreement['of']} unit-hours; "
          f"change marks equal in {agreement['changed_equal']}", cmap=ListedColormap(["white", "#c44e52"]))
    axes[2].set_xlabel("hour")
    fig.suptitle("Table II: commitment of the dispatchable units with 1-hour islanding (filled = on)")
    return fig


def _grid(ax, on: np.ndarray, marked: np.ndarray, units, title: str, cmap=_ON_OFF) -> None:
    ax.imshow(on, cmap=cmap, vmin=0, vmax=1, aspect="auto", extent=(0.5, 24.5, len(units) - 0.5, -0.5))
    for (row, col) in zip(*np.nonzero(marked)):
        ax.add_patch(Rectangle((col + 0.5 + 0.06, row - 0.5 + 0.06), 0.88, 0.88, fill=False, ec="#dd8452", lw=2.5))
    ax.set_xticks(range(1, 25))
    ax.set_yticks(range(len(units)), units)
    ax.set_xticks(np.arange(0.5, 25), minor=True)
    ax.set_yticks(np.arange(-0.5, len(units)), minor=True)
    ax.grid(which="minor", color="0.7", lw=0.5)
    ax.tick_params(which="minor", length=0)
    ax.set_title(title, fontsize=9, loc="left")


def islanding_figure(frame: pd.DataFrame, cost_convention: str, subperiods: int) -> Figure:
    """Fig. 2: cost and its components against the number of islanding hours."""
    fig = figure(figsize=(7, 4.5), constrained_layout=True)
    ax = fig.subplots()
    _cost_lines(ax, frame["island_hours"], frame)
    ax.set_xlabel("islanding hours per scenario, H (h)")
    ax.set_ylabel(cost_label(cost_convention, subperiods))
    ax.set_xticks(frame["island_hours"])
    ax.set_title("Fig. 2: operation cost vs number of islanding hours (penalty c = inf)")
    ax.legend(fontsize=8)
    return fig


_READING_TITLES = {"ceiling": "award as a ceiling: P_M <= P^sch", "take": "award taken while connected: P_M = P^sch"}


def transfer_figure(frame: pd.DataFrame, paper: pd.DataFrame, cost_convention: str, subperiods: int) -> Figure:
    """Fig. 3: cost and its components against the award scale, one panel per reading of the infinite penalty,
    the paper's printed points overlaid on each."""
    readings = list(dict.fromkeys(frame["award"]))
    fig = figure(figsize=(6 * len(readings), 4.8), constrained_layout=True)
    axes = fig.subplots(1, len(readings), sharey=True, squeeze=False)
    factor = float(paper["factor"].iloc[0])
    if cost_convention == "paper" and math.isclose(factor, 1.0):
        how = "paper (as printed)"
    elif cost_convention == "real":
        how = "paper (converted to $ of energy, /6)"
    else:
        how = f"paper (x {subperiods}/6 to {subperiods} sub-periods/h)"
    for ax, reading in zip(axes[0], readings):
        ours = frame[frame["award"] == reading]
        _cost_lines(ax, ours["transfer_scale"], ours)
        for name, marker, color in (("objective", "*", "black"), ("generation", "P", "C0"), ("curtailment", "X", "C2")):
            ax.plot(paper["transfer_scale"], paper[f"{name}_converted"], marker, ms=13, ls="none", color=color,
                    mec="white", zorder=4 if name == "objective" else 3,
                    label=f"{how}: {'total' if name == 'objective' else name}")
        ax.set_xlabel("award P^sch as a multiple of Table I (-)")
        ax.set_xticks(ours["transfer_scale"])
        ax.set_title(_READING_TITLES.get(reading, reading), fontsize=10)
    entries = {label: handle for ax in axes[0] for handle, label in zip(*ax.get_legend_handles_labels())}
    fig.legend(entries.values(), entries.keys(), fontsize=8, loc="outside lower center", ncol=3)  # points fill the axes
    axes[0, 0].set_ylabel(cost_label(cost_convention, subperiods))
    fig.suptitle("Fig. 3: operation cost vs main grid power transfer (1-hour islanding, c = inf)")
    return fig


def dispatch_figure(frame: pd.DataFrame, unit_names) -> Figure:
    """Fig. 4: each dispatchable unit's output at sub-period resolution, islanded hours shaded; P_M and storage below."""
    k = int(frame.index.get_level_values("subperiod").max())
    t = np.arange(len(frame)) / k  # start of each sub-period, hours since midnight
    islanded = frame["connected"].to_numpy() < 0.5
    fig = figure(figsize=(10, 6.5), constrained_layout=True)
    top, bottom = fig.subplots(2, 1, sharex=True)
    for name in unit_names:
        top.step(np.append(t, 24.0), np.append(frame[name], frame[name].iloc[-1]), where="post", label=name, lw=1.6)
    for series, label in (("p_m", "main grid P_M"), ("storage", "storage (+ discharging)"),
                          ("load_shed", "load curtailment LS")):
        bottom.step(np.append(t, 24.0), np.append(frame[series], frame[series].iloc[-1]), where="post", label=label)
    for ax in (top, bottom):
        for n in np.flatnonzero(islanded):
            ax.axvspan(t[n], t[n] + 1.0 / k, color="0.85", lw=0, zorder=0)
        ax.grid(alpha=0.3)
        ax.set_ylabel("power (MW)")
    top.axvspan(0, 0, color="0.85", label="islanded")  # legend entry only
    top.set_title("Fig. 4: generation of the dispatchable units in a scenario islanded in hours "
                  f"{_hour_span(frame, islanded)}")
    top.legend(fontsize=8, ncol=5)
    bottom.axhline(0, color="black", lw=0.6)
    bottom.legend(fontsize=8, ncol=3)
    bottom.set_xlabel("time of day (h); hour t covers [t-1, t)")
    bottom.set_xticks(range(0, 25, 2))
    bottom.set_xlim(0, 24)
    return fig


def _hour_span(frame: pd.DataFrame, islanded: np.ndarray) -> str:
    hours = sorted(set(frame.index.get_level_values("hour")[islanded]))
    return f"{hours[0]}-{hours[-1]}" if hours else "(none)"


def penalty_figure(frame: pd.DataFrame, cost_convention: str, subperiods: int) -> Figure:
    """Fig. 5: cost against the mismatch penalty, categorical x so that c = 0 and c = inf both have a place."""
    fig = figure(figsize=(7, 4.5), constrained_layout=True)
    ax = fig.subplots()
    x = np.arange(len(frame))
    _cost_lines(ax, x, frame)
    ax.set_xticks(x, ["inf" if math.isinf(c) else f"{c:g}" for c in frame["penalty"]])
    ax.set_xlabel("mismatch penalty c ($/MWh above the award; not to scale)")
    ax.set_ylabel(cost_label(cost_convention, subperiods))
    ax.set_title("Fig. 5: operation cost vs penalty for excess main grid transfer (1-hour islanding)")
    ax.legend(fontsize=8)
    return fig
