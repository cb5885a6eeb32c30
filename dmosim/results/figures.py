"""The figure of a recorded day (``dmosim plot``): from a recording's tables (tables.py) to one matplotlib Figure.

Left column, on one time axis: the hourly clearing price (congested hours marked, as the awards say), then for each agent its award P_sch against its metered
import P_M per sub-period. Right column: the day's bill per agent (several days: each agent's daily total), then
beside each agent its deviation penalty and credit per hour. Islanded hours are shaded on every time axis, hours
with no accepted meter report hatched, process restarts dashed. A recording of several market days lays them end
to end on an axis of hours, each day's start labelled with its date. On a feeder a last row shows its prices by bus
and hour, its voltages and its line loading at the peak hour (feeder.py). ``figure_of`` titles it by the run and its
settlement rule.
"""

from __future__ import annotations

import json

import matplotlib

matplotlib.use("Agg")  # files only, never a window: plots are made on headless machines too

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from matplotlib.ticker import FuncFormatter, MultipleLocator  # noqa: E402

from dmo.replay.resettle import day_messages, rule_named  # noqa: E402
from messages.recording import Recording  # noqa: E402

from . import feeder  # noqa: E402

_AWARD, _IMPORT, _ENERGY = "black", "#1f77b4", "#8c9fc4"
_PENALTY, _CREDIT, _ISLANDED = "#d62728", "#2ca02c", "0.85"
_MISSING, _RESTART = "#ff7f0e", "#9467bd"
WIDTH_IN, ROW_IN, DPI = 10.5, 1.75, 120  # 1,260 px wide at DPI; each agent adds a row of ROW_IN inches
FEEDER_IN = 3.2  # the feeder's row (prices by bus, voltages, loading), on a feeder only
_DOLLARS = FuncFormatter(lambda y, _: f"{y:,.0f}")


def figure_of(rec: Recording, frames: dict[str, pd.DataFrame], head: str) -> Figure:
    """The figure of a recording (``dmosim plot``, a run's ``run.png``): its tables ``frames``, titled ``head``, its
    market days and the settlement rule its awards name (so that the runs of a sweep are told apart), with the
    restarts of its processes marked."""
    rules = list(dict.fromkeys(rule_named(award) for _, award in day_messages(rec, None, "award")))
    market_days = sorted(frames["hours"]["market_day"].unique())
    title = f"{head}, {days_label(market_days)}" + (f"\nsettled by {' then '.join(rules)}" if rules else "")
    return recording_figure(frames, title, restarts(rec))


def restarts(rec: Recording) -> pd.DataFrame:
    """(sender, market_day, hour) of each restart of a process: a message of a later ``incarnation`` of its sender
    (docs/protocol.md), placed at the hour the DMO's clock last announced (0: before its first real-time hour)."""
    seen: dict[str, int] = {}
    at, rows = ("", 0), []
    for m in rec.messages:
        if m.invalid is not None:
            continue
        try:
            msg = json.loads(m.payload)
        except ValueError:
            continue
        if m.kind == "clock":
            at = (msg.get("market_day", ""), msg.get("hour") or (24 if msg.get("phase") == "settlement" else 0))
        sender, incarnation = msg.get("sender"), msg.get("incarnation")
        if not sender or not incarnation:
            continue
        if sender in seen and incarnation > seen[sender]:
            rows.append({"sender": sender, "market_day": at[0], "hour": at[1]})
        seen[sender] = max(incarnation, seen.get(sender, 0))
    return pd.DataFrame(rows, columns=["sender", "market_day", "hour"])


def recording_figure(frames: dict[str, pd.DataFrame], title: str = "",
                     restarted: pd.DataFrame | None = None) -> Figure:
    """The figure of the tables ``frames`` (``dmosim.results.tables.tables``); needs at least one statement.
    ``restarted`` (``restarts``) marks where a process was restarted."""
    hours, meter, days = frames["hours"], frames["meter"], frames["days"]
    if hours.empty:
        raise ValueError("no settlement statement recorded: nothing to plot")
    market_days = sorted(hours["market_day"].unique())
    agents = sorted(hours["agent"].unique())
    start = {day: 24 * i for i, day in enumerate(market_days)}  # x: hours from the start of the first day
    hours = hours.assign(t=hours["market_day"].map(start) + hours["hour"] - 1).sort_values(["agent", "t"])

    on_feeder = not frames.get("network", pd.DataFrame()).empty
    fig = plt.figure(figsize=(WIDTH_IN, ROW_IN * (1 + len(agents)) + 1.2 + FEEDER_IN * on_feeder), dpi=DPI,
                     layout="constrained")
    rows = fig.add_gridspec(2 if on_feeder else 1, 1, height_ratios=(ROW_IN * (1 + len(agents)), FEEDER_IN)
                            if on_feeder else None)
    grid = rows[0].subgridspec(1 + len(agents), 2, width_ratios=(3, 2))
    if on_feeder:
        feeder.draw(fig, rows[1].subgridspec(1, 3, width_ratios=(3, 2, 2)), frames, start)
    price_ax = fig.add_subplot(grid[0, 0])
    power_axes = [fig.add_subplot(grid[1 + i, 0], sharex=price_ax) for i in range(len(agents))]
    money_axes = [fig.add_subplot(grid[1 + i, 1], sharex=price_ax) for i in range(len(agents))]

    per_hour = hours.drop_duplicates(["market_day", "hour"])
    # on a feeder every bus has its price (the heat map below): the one common to all is the substation's
    price = "energy_price_per_mwh" if on_feeder else "clearing_price_per_mwh"
    _hourly_stairs(price_ax, per_hour, price, color=_AWARD)
    for where, marker in (("import", "^"), ("export", "v"), ("line", "s"), ("voltage", "D")):
        congested = per_hour[(per_hour["congestion"] == where).fillna(False)]  # <NA>: not stated, not marked
        if not congested.empty:
            price_ax.plot(congested["t"] + 0.5, congested[price], marker, color=_PENALTY, ms=5,
                          ls="none", label=f"{where} {'limit binds' if where in ('line', 'voltage') else 'congestion'}"
                                           " (as the clearing decided)")
    price_ax.set_ylabel("$/MWh")
    price_ax.set_title("the substation's price per hour" if on_feeder else "clearing price per hour", loc="left",
                       fontsize=10)
    credit = bool((hours["deviation_credit"] != 0).any())  # a credit of 0 throughout: nothing to draw or name
    for agent, power, money in zip(agents, power_axes, money_axes):
        own = hours[hours["agent"] == agent]
        _power(power, agent, own, meter[meter["agent"] == agent], start)
        _penalties(money, agent, own, credit)
        reported = meter.loc[meter["agent"] == agent, ["market_day", "hour"]].drop_duplicates().assign(reported=True)
        missing = own.merge(reported, on=["market_day", "hour"], how="left")
        missing = missing.loc[missing["reported"].isna().to_numpy() | (missing["missing_subperiods"] > 0).to_numpy(),
                              "t"].to_numpy()
        power.broken_barh([(t, 1) for t in missing], (0, 1), transform=power.get_xaxis_transform(), zorder=0.5,
                          facecolor="none", edgecolor=_MISSING, hatch="///", lw=0,
                          label="hour with no accepted meter report (missing-data rule)" if len(missing) else None)
    if restarted is not None:
        places = restarted.assign(t=restarted["market_day"].map(start) + (restarted["hour"] - 1).clip(lower=0))
        places = places.dropna(subset="t")  # the start of the hour it happened in
        for sender, t in zip(places["sender"], places["t"]):
            axes = [price_ax] if sender not in agents else [power_axes[agents.index(sender)]]
            for ax in axes:
                ax.axvline(t, color=_RESTART, lw=1.5, ls="--", zorder=4,
                           label=f"process restarted ({'the DMO' if ax is price_ax else 'the agent'})")

    islanded = hours.loc[hours["islanded"], "t"].drop_duplicates().to_numpy()
    xlabel = "time of day, h" if len(market_days) == 1 else "hour of the market day (each day's start: its date)"
    for ax in [price_ax, *power_axes, *money_axes]:
        ax.broken_barh([(t, 1) for t in islanded], (0, 1), transform=ax.get_xaxis_transform(), color=_ISLANDED,
                       zorder=0, lw=0)
        _time_axis(ax, market_days)
        ax.grid(axis="y", alpha=0.3)
        if ax not in (power_axes[-1], money_axes[-1]):
            ax.tick_params(which="both", labelbottom=False)
        else:
            ax.set_xlabel(xlabel)

    totals_ax = fig.add_subplot(grid[0, 1])
    if len(market_days) == 1:
        _bill(totals_ax, days, agents)
    else:
        _daily_totals(totals_ax, days, market_days, agents)
    handles = {}  # one entry per label, whichever axis drew it
    for ax in [price_ax, *power_axes, *money_axes]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    handles = [*handles.values(), Patch(color=_ISLANDED, label="islanded hour (grid state)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 3), fontsize=9, frameon=False)
    fig.suptitle(title or days_label(market_days), fontsize=12)
    return fig


def days_label(market_days: list[str]) -> str:
    """"market day D", or "market days D1 to Dn (n)"."""
    if len(market_days) == 1:
        return f"market day {market_days[0]}"
    return f"market days {market_days[0]} to {market_days[-1]} ({len(market_days)})"


def _power(ax, agent: str, hours: pd.DataFrame, meter: pd.DataFrame, start: dict[str, int]) -> None:
    """The agent's award, hour by hour, against its metered import, sub-period by sub-period, MW."""
    _hourly_stairs(ax, hours, "p_sch_mw", color=_AWARD, lw=1.6, label="award P_sch")
    label = "metered import P_M per sub-period (gap: not reported)"
    for day, readings in meter.groupby("market_day", sort=False):
        k = int(readings["subperiod"].max())
        slot = (readings["hour"].to_numpy() - 1) * k + readings["subperiod"].to_numpy() - 1
        values = np.full(24 * k, np.nan)
        values[slot] = readings["p_m_mw"].to_numpy()
        ax.stairs(values, start[day] + np.arange(24 * k + 1) / k, baseline=None, color=_IMPORT, lw=1.2, label=label)
        label = None
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_ylabel("MW")
    ax.set_title(f"{agent}: award and metered import (negative: export)", loc="left", fontsize=10)


def _penalties(ax, agent: str, hours: pd.DataFrame, credit: bool) -> None:
    """The agent's deviation penalty per hour, $, and its credit drawn below 0 (it lowers the bill), if any agent
    has one."""
    middle = hours["t"].to_numpy() + 0.5
    ax.bar(middle, hours["deviation_penalty"], width=0.8, color=_PENALTY, label="deviation penalty")
    if credit:
        ax.bar(middle, -hours["deviation_credit"], width=0.8, color=_CREDIT, label="deviation credit (drawn below 0)")
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_ylabel("$")
    ax.yaxis.set_major_formatter(_DOLLARS)
    ax.set_title(f"{agent}: deviation penalty" + (" and credit" if credit else "") + " per hour", loc="left",
                 fontsize=10)


def _hourly_stairs(ax, frame: pd.DataFrame, column: str, **style) -> None:
    """One value per hour as a step line, each market day its own line."""
    for _, day in frame.groupby("market_day", sort=False):
        t = day["t"].to_numpy()
        ax.stairs(day[column].to_numpy(), np.append(t, t[-1] + 1), baseline=None, **style)
        style.pop("label", None)


def _time_axis(ax, market_days: list[str]) -> None:
    span = 24 * len(market_days)
    ax.set_xlim(0, span)
    if len(market_days) == 1:
        ax.xaxis.set_major_locator(MultipleLocator(3))
        ax.xaxis.set_minor_locator(MultipleLocator(1))
        return
    every = max(1, -(-len(market_days) // 8))  # at most eight dates along the axis
    ax.set_xticks(range(0, span, 24 * every), [f"0\n{d}" for d in _short(market_days)[::every]])
    ax.xaxis.set_minor_locator(MultipleLocator(6 if len(market_days) <= 4 else 12))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda x, _: f"{x % 24:.0f}" if x % 24 else ""))
    ax.tick_params(axis="x", which="minor", labelsize=7)
    for boundary in range(24, span, 24):
        ax.axvline(boundary, color="0.4", lw=0.8, ls=":")


def _short(market_days: list[str]) -> list[str]:
    """Dates as MM-DD when they share a year (the title says which), else as they are."""
    return [d[5:] for d in market_days] if len({d[:4] for d in market_days}) == 1 else list(market_days)


def _bill(ax, days: pd.DataFrame, agents: list[str]) -> None:
    """One day's bill per agent, $: energy charge and deviation penalty stacked (a negative energy charge, an
    export paid for, below 0), the credit below 0, the total marked and written above."""
    bill = days.set_index("agent").reindex(agents)
    x = np.arange(len(agents))
    up, down = np.zeros(len(agents)), np.zeros(len(agents))
    parts = (("energy charge", bill["energy_charge"], _ENERGY),
             ("deviation penalty", bill["deviation_penalty"], _PENALTY),
             ("deviation credit", -bill["deviation_credit"], _CREDIT))
    for label, values, color in [p for p in parts if p[0] != "deviation credit" or (p[1] != 0).any()]:
        values = values.to_numpy(dtype=float)
        ax.bar(x, values, bottom=np.where(values >= 0, up, down), width=0.6, color=color, label=label)
        up, down = up + np.clip(values, 0, None), down + np.clip(values, None, 0)
    total = bill["total"].to_numpy(dtype=float)
    ax.hlines(total, x - 0.36, x + 0.36, color="black", lw=2, zorder=3, label="total")
    crowded = len(agents) > 5  # past five bars the amounts stand upright, or they run into each other
    for xi, top, value in zip(x, up, total):
        ax.annotate(f"{'-' if value < 0 else ''}${abs(value):,.2f}", (xi, top), xytext=(0, 3),
                    textcoords="offset points", ha="center", fontsize=7 if crowded else 8,
                    rotation=90 if crowded else 0, va="bottom")
    low, high = min(down.min(), 0.0), max(up.max(), 0.0)
    room = 0.9 if crowded else 0.4  # above the bars: the amounts (upright ones are taller) and the legend
    ax.set_ylim(low - 0.1 * (high - low), high + room * (high - low) + 1e-9)
    ax.set_xticks(x, agents, rotation=45 if crowded else 0, fontsize=8 if crowded else None)
    ax.set_xlim(-0.6, len(agents) - 0.4)
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_ylabel("$")
    ax.yaxis.set_major_formatter(_DOLLARS)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title("the day's bill per agent: energy charge + penalty - credit", loc="left", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # beside: covers no label


def _daily_totals(ax, days: pd.DataFrame, market_days: list[str], agents: list[str]) -> None:
    """Each agent's total of each day, $, one line per agent."""
    totals = days.pivot_table(index="market_day", columns="agent", values="total", aggfunc="sum").reindex(
        index=market_days, columns=agents)
    x = np.arange(len(market_days))
    for agent in agents:
        ax.plot(x, totals[agent].to_numpy(dtype=float), "o-", label=agent)
    every = max(1, -(-len(market_days) // 8))
    ax.set_xticks(x[::every], _short(market_days)[::every])
    ax.set_xlim(-0.5, len(market_days) - 0.5)
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_xlabel("market day")
    ax.set_ylabel("$")
    ax.yaxis.set_major_formatter(_DOLLARS)
    ax.grid(alpha=0.3)
    ax.set_title("daily total per agent (what it owes)", loc="left", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # beside: covers no point
