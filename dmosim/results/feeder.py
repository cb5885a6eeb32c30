"""The feeder's panels of a run's figure (``dmosim plot``, ``run.png``) on a feeder: the price of every bus in every
hour as a heat map, the voltage along the feeder at the peak hour, and each line's loading at that hour."""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.colors import TwoSlopeNorm

_PLAN, _REALISED, _LIMIT = "#1f77b4", "#ff7f0e", "#d62728"


def peak_hour(network: pd.DataFrame) -> tuple[str, int]:
    """(market day, hour) of the plan's largest import at the substation: where a feeder is most stressed."""
    plan = network[network["stage"] == "plan"]
    row = plan.loc[plan["substation_mw"].idxmax()]
    return row["market_day"], int(row["hour"])


def draw(fig, cells, frames: dict[str, pd.DataFrame], start: dict[str, int]) -> None:
    """The three panels in the gridspec ``cells`` (one row, three columns) of ``fig``, from the tables' ``network``,
    ``buses`` and ``lines``; ``start`` gives each market day's first hour on the run's time axis."""
    network, buses, lines = frames["network"], frames["buses"], frames["lines"]
    heat_ax, volt_ax, load_ax = (fig.add_subplot(cells[0, i]) for i in range(3))
    _prices(heat_ax, buses[buses["stage"] == "plan"], start)
    day, hour = peak_hour(network)
    at = lambda frame: frame[(frame["market_day"] == day) & (frame["hour"] == hour)]  # noqa: E731
    _voltages(volt_ax, at(buses), at(network), day, hour)
    _loading(load_ax, at(lines))


def _prices(ax, plan: pd.DataFrame, start: dict[str, int]) -> None:
    """Bus x hour, coloured by the bus's price less the hour's lowest: where, and when, prices separate."""
    order = list(dict.fromkeys(plan["bus"]))
    t = plan["market_day"].map(start) + plan["hour"] - 1
    grid = plan.assign(t=t).pivot_table(index="bus", columns="t", values="bus_price_per_mwh").reindex(order)
    spread = grid - grid.min(axis=0)
    top = max(float(np.nanmax(spread.to_numpy())), 1e-9)
    image = ax.imshow(spread.to_numpy(dtype=float), aspect="auto", cmap="magma_r", interpolation="nearest",
                      extent=(grid.columns.min(), grid.columns.max() + 1, len(order) - 0.5, -0.5),
                      norm=TwoSlopeNorm(vcenter=top / 2, vmin=0, vmax=top))
    step = label_step(len(order), 12)  # at most 12 bus labels, so 33 (or 1,000) buses stay legible
    ax.set_yticks(range(0, len(order), step), order[::step], fontsize=7)
    ax.set_ylabel("bus (feeder order)")
    ax.set_xlabel("hour")
    ax.set_title("bus price above the hour's lowest, $/MWh", loc="left", fontsize=10)
    ax.figure.colorbar(image, ax=ax, fraction=0.05, pad=0.02)


def _voltages(ax, buses: pd.DataFrame, network: pd.DataFrame, day: str, hour: int) -> None:
    """Each bus's voltage at the peak hour, planned and realised (LinDistFlow), with the AC lowest marked."""
    for stage, color in (("plan", _PLAN), ("realised", _REALISED)):
        own, ac = buses[buses["stage"] == stage], network[network["stage"] == stage]
        if own.empty:
            continue
        ax.plot(range(len(own)), own["voltage_pu"], ".-", color=color, ms=3, lw=1, label=f"{stage} (LinDistFlow)")
        position = {bus: i for i, bus in enumerate(own["bus"])}
        lowest = ac["ac_v_min_bus"].iloc[0] if not ac.empty else None
        if lowest in position:  # an hour with no AC solution names no bus
            ax.plot(position[lowest], ac["ac_v_min_pu"].iloc[0], "x", color=color, ms=7, label=f"{stage}: AC lowest")
    order = list(dict.fromkeys(buses["bus"]))
    step = label_step(len(order), 8)
    ax.set_xticks(range(0, len(order), step), order[::step], fontsize=7)
    ax.set_xlabel("bus (feeder order)")
    ax.set_ylabel("V, p.u.")
    ax.set_title(f"voltage, {day} hour {hour} (peak)", loc="left", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")


def _loading(ax, lines: pd.DataFrame) -> None:
    """Each line's loading at the peak hour, planned and realised, against its limit (1)."""
    plan, real = (lines[lines["stage"] == s] for s in ("plan", "realised"))
    x = np.arange(len(plan))
    ax.bar(x - 0.2, plan["loading"], 0.4, color=_PLAN, label="plan")
    if len(real) == len(plan):
        ax.bar(x + 0.2, real["loading"], 0.4, color=_REALISED, label="realised")
    ax.axhline(1.0, color=_LIMIT, lw=1, ls="--", label="thermal limit")
    step = label_step(len(plan), 8)
    ax.set_xticks(x[::step], list(plan["line"])[::step], fontsize=7, rotation=45)
    ax.set_ylim(0, 1.45 * max(1.0, float(lines["loading"].max())))  # room for the legend above the limit
    ax.set_ylabel("S / S max (LinDistFlow)")
    ax.set_title("line loading, peak hour", loc="left", fontsize=10)
    ax.legend(fontsize=7, loc="upper left", ncol=2, frameon=False)


def label_step(n: int, labels: int) -> int:
    """Every how many ticks to label so that at most ``labels`` labels show."""
    return max(1, -(-n // labels))
