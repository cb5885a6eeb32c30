"""The panels of a run's figure with many agents (figures.py, above ``COMPACT_AGENTS``): each agent's deviation and
penalty as one row of an agents x hours heat map, and the bills ranked, so that the figure keeps its size whatever
the number of agents."""

from __future__ import annotations

import matplotlib
import numpy as np
import pandas as pd
from matplotlib.colors import LinearSegmentedColormap, Normalize, TwoSlopeNorm
from matplotlib.patches import Rectangle

from .feeder import label_step
from .style import CREDIT, DOLLARS, ENERGY, MISSING, PENALTY, RESTART, short_dates

COMPACT_AGENTS = 8  # more agents than this: a heat-map row each, not two panels (9 agents: 19 in tall, 24 on a feeder)
AGENT_IN, MAPS_IN = 0.11, (2.8, 6.6)  # a heat map's row per agent, inches, and the maps' least and most height
MAP_TEXT_IN = 0.6  # of the maps' height, what their title and the hours below them take
LABEL_IN = 0.11  # room for one agent's name along a heat map (7 pt), inches: fewer names where rows are thinner
HOURLY_DAYS = 7  # the penalty map is by hour up to a week (168 columns, ~3 px each), by day beyond
RANKED = 5  # the bills panel: the RANKED highest and RANKED lowest totals, the others as their mean
_DEVIATION = "RdBu_r"  # red: imported more than awarded (the penalised side), blue: less
_PENALTIES = LinearSegmentedColormap.from_list("penalty", ["white", PENALTY])
_NET = LinearSegmentedColormap.from_list("net", [CREDIT, "white", PENALTY])
_NO_DATA = "0.8"


def maps_height(agents: int) -> float:
    """The height of the heat maps' row, inches: a row per agent, and their text, within bounds."""
    return float(np.clip(MAP_TEXT_IN + AGENT_IN * agents, *MAPS_IN))


def agent_grid(hours: pd.DataFrame, column: str, agents: list[str], span: int) -> np.ndarray:
    """Agents x columns ``t`` of ``column`` summed (``hours`` with its ``t``: hours from the start of the first day,
    or days); NaN where an agent has no line or only NaN."""
    summed = hours.groupby(["agent", "t"])[column].sum(min_count=1)  # a cell of NaN only stays NaN, not 0
    return summed.unstack("t").reindex(index=agents, columns=range(span)).to_numpy(dtype=float)


def deviation_map(ax, hours: pd.DataFrame, agents: list[str], span: int):
    """Each agent's metered import less its award per hour, MWh (MW over the hour), red above, blue below, white
    at 0, on limits symmetric about 0. An hour the missing-data rule settled (``missing``) has no metered import:
    it is left grey (the rule's import, the agent's maximum, would set the colours' scale) and hatched. Returns
    the image, for its colour bar."""
    measured = hours.assign(d=(hours["import_mwh"] - hours["p_sch_mw"]).where(~hours["missing"]))
    grid = agent_grid(measured, "d", agents, span)
    top = max(float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 0.0, 1e-3)
    image = _image(ax, grid, _DEVIATION, Normalize(-top, top), span)
    ax.set_title("deviation per hour: metered import - award, MWh", loc="left", fontsize=10)
    return image


def penalty_hours(days: int) -> int:
    """The hours a column of the penalty map holds: 1, or 24 beyond ``HOURLY_DAYS`` days."""
    return 24 if days > HOURLY_DAYS else 1


def penalty_map(ax, hours: pd.DataFrame, agents: list[str], span: int, credit: bool):
    """Each agent's deviation penalty per hour, $ (with credits, the penalty less the credit: green below 0), by day
    beyond ``HOURLY_DAYS`` days. The colours stop at the largest amount of a metered hour, so that the missing-data
    rule's (hatched) do not wash out the rest: a larger one takes the end colour and the bar says so. Returns the
    image, for its colour bar."""
    per = penalty_hours(span // 24)
    net = hours.assign(net=hours["deviation_penalty"] - hours["deviation_credit"], t=hours["t"] // per,
                       m=hours["missing"].astype(float))
    grid = agent_grid(net, "net", agents, span // per)
    metered = agent_grid(net, "m", agents, span // per) == 0  # a cell with a line and every hour of it metered
    top = max(float(np.nanmax(np.abs(np.where(metered, grid, np.nan)))) if metered.any() else 0.0, 1e-2)
    norm = TwoSlopeNorm(0.0, -top, top) if credit else Normalize(0.0, top)
    image = _image(ax, grid, _NET if credit else _PENALTIES, norm, span // per)
    if per > 1:
        dates = short_dates(sorted(hours["market_day"].unique()))
        step = label_step(len(dates), 6)
        ax.set_xticks(np.arange(0, len(dates), step) + 0.5, dates[::step], fontsize=8)
        ax.set_xlabel("market day")
    ax.set_title("deviation penalty" + (" - credit" if credit else "") + (" per day" if per > 1 else " per hour")
                 + ", $", loc="left", fontsize=10)
    return image


def colour_bar(fig, image, ax, label: str, dollars: bool = False) -> None:
    """A slim colour bar right of ``ax``, arrowed at an end where values go beyond it."""
    data, norm = image.get_array(), image.norm
    over, under = bool(np.nanmax(data) > norm.vmax), bool(np.nanmin(data) < norm.vmin)
    extend = {(True, True): "both", (True, False): "max", (False, True): "min"}.get((over, under), "neither")
    bar = fig.colorbar(image, ax=ax, fraction=0.04, pad=0.015, aspect=40, extend=extend)
    bar.ax.tick_params(labelsize=7)
    bar.set_label(label, fontsize=8)
    if dollars:
        bar.ax.yaxis.set_major_formatter(DOLLARS)


def mark_missing(ax, hours: pd.DataFrame, agents: list[str], label: str, per: int = 1) -> None:
    """Hatch each agent's hours with no accepted meter report (``missing``); ``per``: hours a column holds."""
    for row, agent in enumerate(agents):
        at = np.unique(hours.loc[(hours["agent"] == agent) & hours["missing"], "t"].to_numpy() // per)
        ax.broken_barh([(t, 1) for t in at], (row - 0.5, 1), facecolor="none", edgecolor=MISSING, hatch="////",
                       lw=0, zorder=2, label=label if len(at) else None)
        label = None if len(at) else label


def mark_restarts(ax, places: pd.DataFrame, agents: list[str], label: str) -> None:
    """A diamond on an agent's row at the start of the hour its process was restarted in (``places``: sender, t)."""
    own = places[places["sender"].isin(agents)]
    rows = own["sender"].map({agent: i for i, agent in enumerate(agents)})
    ax.plot(own["t"], rows, "D", color=RESTART, ms=5, mec="white", mew=0.6, ls="none", zorder=4,
            label=label if not own.empty else None)


def frame_islanded(ax, islanded: np.ndarray, rows: int, span: int) -> None:
    """Outline each run of islanded hours across every row (shading would hide the colours); thinner over many
    days, where a frame is a few pixels wide."""
    for start, length in _runs(np.sort(islanded)):
        ax.add_patch(Rectangle((start, -0.5), length, rows, facecolor="none", edgecolor="0.2",
                               lw=1.2 if span <= 72 else 0.5, zorder=3))


def ranked_bills(ax, days: pd.DataFrame, agents: list[str], n_days: int) -> None:
    """Each agent's bill over the run, $, energy charge and penalty stacked to the right when positive, the credit
    to the left, sorted from the highest total down: the ``RANKED`` highest and lowest, and between them the mean
    of the others, each total marked and written."""
    bill = days.groupby("agent")[["energy_charge", "deviation_penalty", "deviation_credit", "total"]].sum()
    bill = bill.reindex(agents).fillna(0.0).sort_values("total", ascending=False, kind="stable")
    names = list(bill.index)
    if len(bill) > 2 * RANKED + 1:
        middle = bill.iloc[RANKED:-RANKED]
        bill = pd.concat([bill.iloc[:RANKED], middle.mean().to_frame(f"{len(middle)} others (mean)").T,
                          bill.iloc[-RANKED:]])
        names = list(bill.index)
    y = np.arange(len(bill))
    parts, right, left = stacked(bill)
    for label, values, base, color in parts:
        ax.barh(y, values, left=base, height=0.7, color=color, label=label)
    total = bill["total"].to_numpy(dtype=float)
    ax.vlines(total, y - 0.42, y + 0.42, color="black", lw=2, zorder=3, label="total of the bill")
    low, high = min(left.min(), 0.0), max(right.max(), 0.0)
    for yi, end, value in zip(y, right, total):
        ax.annotate(f"{'-' if value < 0 else ''}${abs(value):,.2f}", (max(end, 0.0), yi), xytext=(3, 0),
                    textcoords="offset points", va="center", fontsize=7)
    ax.set_xlim(low - 0.05 * (high - low), high + 0.35 * (high - low) + 1e-9)  # room for the amounts
    ax.set_yticks(y, names, fontsize=7)
    ax.set_ylim(len(bill) - 0.5, -0.5)
    ax.axvline(0, color="0.5", lw=0.6)
    ax.xaxis.set_major_formatter(DOLLARS)
    ax.tick_params(axis="x", labelsize=7)
    ax.grid(axis="x", alpha=0.3)
    what = "the day's bill" if n_days == 1 else f"{n_days} days' bill"
    which = f"top and bottom {RANKED} of {len(agents)}" if len(names) < len(agents) else "highest first"
    ax.set_title(f"{what}, $ ({which})", loc="left", fontsize=10)


def stacked(bill: pd.DataFrame) -> tuple[list[tuple[str, np.ndarray, np.ndarray, str]], np.ndarray, np.ndarray]:
    """The parts of each bill (rows of ``energy_charge``, ``deviation_penalty``, ``deviation_credit``) as bars to
    stack from 0, positive ones outward one way, negative ones (a credit, an export paid for) the other: (label,
    values, where each bar starts, colour), the credit only if one is not 0; and where the stacks end each way."""
    up, down, parts = np.zeros(len(bill)), np.zeros(len(bill)), []
    for label, column, sign, color in (("energy charge", "energy_charge", 1, ENERGY),
                                       ("deviation penalty", "deviation_penalty", 1, PENALTY),
                                       ("deviation credit", "deviation_credit", -1, CREDIT)):
        values = sign * bill[column].to_numpy(dtype=float)
        if column == "deviation_credit" and not values.any():
            continue
        parts.append((label, values, np.where(values >= 0, up, down), color))
        up, down = up + np.clip(values, 0, None), down + np.clip(values, None, 0)
    return parts, up, down


def _image(ax, grid: np.ndarray, cmap, norm, columns: int):
    cmap = (matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap).with_extremes(bad=_NO_DATA)
    return ax.imshow(np.ma.masked_invalid(grid), aspect="auto", cmap=cmap, norm=norm, interpolation="nearest",
                     extent=(0, columns, grid.shape[0] - 0.5, -0.5))


def agent_axis(ax, agents: list[str], height_in: float) -> None:
    """Agents down an axis ``height_in`` inches tall, every k-th named so that no two names overlap."""
    step = label_step(len(agents), max(1, int((height_in - MAP_TEXT_IN) / LABEL_IN)))
    ax.set_yticks(range(0, len(agents), step), agents[::step], fontsize=7)
    ax.set_ylabel("agent" + (f" (one in {step} named)" if step > 1 else ""))


def _runs(ts: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive integers as (first, how many)."""
    runs: list[tuple[int, int]] = []
    for t in ts.astype(int):
        if runs and runs[-1][0] + runs[-1][1] == t:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((int(t), 1))
    return runs
