"""The figure of a recorded day (``dmosim plot``): from a recording's tables (tables.py) to one matplotlib Figure.

Left column, on one time axis: the hourly clearing price (congested hours marked, as the awards say), then for each agent its award P_sch against its metered
import P_M per sub-period. Right column: the day's bill per agent (several days: each agent's daily total), then
beside each agent its deviation penalty and credit per hour. Islanded hours are shaded on every time axis, hours
with no accepted meter report hatched, process restarts dashed. With more than ``COMPACT_AGENTS`` agents the
figure is compact instead (compact.py): below the price, agents x hours heat maps of the deviation and of the
penalty, and beside the price the bills ranked, so that its size stays bounded at hundreds of agents. A recording
of several market days lays them end to end on an axis of hours, each day's start labelled with its date. On a
feeder two last rows show its prices by bus and hour on the same time axis, then at one hour its voltage along
each branch and its lines' loading as the clearing limits it (feeder.py). ``figure_of`` titles it by the run and
its settlement rule.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FuncFormatter, MultipleLocator

from dmo.replay.resettle import day_messages, rule_named
from messages.recording import Recording

from . import feeder
from .compact import (COMPACT_AGENTS, agent_axis, colour_bar, deviation_map,
                      frame_islanded, maps_height, mark_missing, mark_restarts, penalty_hours, penalty_map,
                      ranked_bills, stacked)
from .order import natural
from .style import CREDIT, DOLLARS, ISLANDED, MISSING, PENALTY, RESTART, figure, short_dates

_AWARD, _IMPORT = "black", "#1f77b4"
WIDTH_IN, ROW_IN, DPI = 10.5, 1.75, 120  # 1,260 px wide at DPI; each agent adds a row of ROW_IN inches
TOP_IN = 2.4  # the price's row with many agents: the ranked bills beside it need the room
_MISSING_LABEL = "hour with no accepted meter report (missing-data rule)"
_DMO_RESTARTED = "process restarted (the DMO)"


def figure_of(rec: Recording, frames: dict[str, pd.DataFrame], head: str) -> Figure:
    """The figure of a recording (``dmosim plot``, a run's ``run.png``): its tables ``frames``, titled ``head``, its
    market days and the settlement rule its awards name (so that the runs of a sweep are told apart), with the
    restarts of its processes marked."""
    rules = list(dict.fromkeys(rule_named(award) for _, award in day_messages(rec, None, "award")))
    market_days = sorted(frames["hours"]["market_day"].unique())
    title = f"{head}, {days_label(market_days)}" + (f"\nsettled by {' then '.join(rules)}" if rules else "")
    on_feeder = not frames.get("network", pd.DataFrame()).empty
    return recording_figure(frames, title, restarts(rec), feeder.voltage_limits(rec) if on_feeder else None)


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


def recording_figure(frames: dict[str, pd.DataFrame], title: str = "", restarted: pd.DataFrame | None = None,
                     voltage_limits: tuple[float, float] | None = None) -> Figure:
    """The figure of the tables ``frames`` (``dmosim.results.tables.tables``); needs at least one statement.
    ``restarted`` (``restarts``) marks where a process was restarted. Up to ``COMPACT_AGENTS`` agents each has its
    row of panels; more share heat maps (compact.py), so the figure's size does not grow with them. On a feeder,
    ``voltage_limits`` (v_min, v_max) are drawn on its voltage panel (``feeder.voltage_limits``)."""
    hours, meter, days = frames["hours"], frames["meter"], frames["days"]
    if hours.empty:
        raise ValueError("no settlement statement recorded: nothing to plot")
    market_days = sorted(hours["market_day"].unique())
    agents = sorted(hours["agent"].unique(), key=natural)
    start = {day: 24 * i for i, day in enumerate(market_days)}  # x: hours from the start of the first day
    hours = hours.assign(t=hours["market_day"].map(start) + hours["hour"] - 1, missing=_missing(hours, meter))
    hours = hours.sort_values(["agent", "t"])
    places = pd.DataFrame(columns=["sender", "t"]) if restarted is None else restarted.assign(
        t=restarted["market_day"].map(start) + (restarted["hour"] - 1).clip(lower=0)).dropna(subset="t")
    compact = len(agents) > COMPACT_AGENTS

    on_feeder = not frames.get("network", pd.DataFrame()).empty
    market_in = TOP_IN + maps_height(len(agents)) if compact else ROW_IN * (1 + len(agents))
    below = (feeder.HEAT_IN, feeder.LOADING_IN) if on_feeder else ()  # the feeder's rows, in the market's grid
    fig = figure(figsize=(WIDTH_IN, market_in + 1.2 + sum(below)), dpi=DPI, layout="constrained")
    draw = _compact if compact else _per_agent
    price_ax, time_axes, grid = draw(fig, hours, meter, days, agents, start, places, below)
    _price(price_ax, hours, on_feeder)
    heat_ax = None
    if on_feeder:  # in the same grid, so that its heat map's columns stand under the hours above
        heat_ax = feeder.draw(fig, (grid[-2, 0], grid[-2, 1], grid[-1, :]), frames, start, price_ax, voltage_limits)
    for t in places.loc[~places["sender"].isin(agents), "t"]:
        price_ax.axvline(t, color=RESTART, lw=1.5, ls="--", zorder=4, label=_DMO_RESTARTED)

    islanded = hours.loc[hours["islanded"], "t"].drop_duplicates().to_numpy()
    xlabel = "time of day, h" if len(market_days) == 1 else "hour of the market day (each day's start: its date)"
    for ax in time_axes:
        if not compact or ax is price_ax:
            ax.broken_barh([(t, 1) for t in islanded], (0, 1), transform=ax.get_xaxis_transform(), color=ISLANDED,
                           zorder=0, lw=0)
            ax.grid(axis="y", alpha=0.3)
        else:
            frame_islanded(ax, islanded, len(agents), 24 * len(market_days))
        _time_axis(ax, market_days)
        if ax is price_ax or not compact and ax not in time_axes[-2:]:
            ax.tick_params(which="both", labelbottom=False)
        else:
            ax.set_xlabel(xlabel)
    if heat_ax is not None:
        _time_axis(heat_ax, market_days)
        heat_ax.tick_params(which="both", labelbottom=True)  # sharing x with the price, whose labels are off
        heat_ax.set_xlabel(xlabel)

    handles = {}  # one entry per label, whichever axis drew it
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if ax.get_legend() is None:  # a panel's own legend (the bills') says its own
                handles.setdefault(label, handle)
    islanded_label = "islanded hour (grid state" + ("; framed on the maps)" if compact else ")")
    handles = [*handles.values(), Patch(facecolor=ISLANDED, edgecolor="0.2" if compact else ISLANDED,
                                        label=islanded_label)]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 3), fontsize=9, frameon=False)
    fig.suptitle((title or days_label(market_days)) + stopped_short(frames.get("schedules"), len(market_days)),
                 fontsize=12)
    return fig


def stopped_short(schedules: pd.DataFrame | None, days: int, shown: int = 4) -> str:
    """A line for the figure's title naming the schedules whose solve stopped short of its gap (the ``schedules``
    table's ``stopped_short``), the first ``shown`` of them and how many more; empty if none did (or no table)."""
    if schedules is None or not schedules["stopped_short"].any():
        return ""
    short = schedules[schedules["stopped_short"]]
    named = [f"{row.agent}{f' {row.market_day}' if days > 1 else ''} ({row.status}"
             f"{'' if pd.isna(row.mip_gap) else f', gap {100 * row.mip_gap:.2f}%'})"
             for row in short.head(shown).itertuples()]
    more = f" and {len(short) - shown} more" if len(short) > shown else ""
    return f"\nschedules stopped short of their gap: {', '.join(named)}{more}"


def _per_agent(fig, hours, meter, days, agents, start, places, below):
    """Up to ``COMPACT_AGENTS`` agents: the price, then each agent's award against its metered import and, beside,
    its penalties per hour; the bills beside the price. Returns the price's axes, every axes on the time axis (the
    two lowest last) and the grid, whose last rows, of heights ``below`` (inches), are left for the caller."""
    grid = fig.add_gridspec(1 + len(agents) + len(below), 2, width_ratios=(3, 2),
                            height_ratios=[ROW_IN] * (1 + len(agents)) + list(below))
    price_ax = fig.add_subplot(grid[0, 0])
    power_axes = [fig.add_subplot(grid[1 + i, 0], sharex=price_ax) for i in range(len(agents))]
    money_axes = [fig.add_subplot(grid[1 + i, 1], sharex=price_ax) for i in range(len(agents))]
    credit = bool((hours["deviation_credit"] != 0).any())  # a credit of 0 throughout: nothing to draw or name
    for agent, power, money in zip(agents, power_axes, money_axes):
        own = hours[hours["agent"] == agent]
        _power(power, agent, own, meter[meter["agent"] == agent], start)
        _penalties(money, agent, own, credit)
        missing = own.loc[own["missing"], "t"].to_numpy()
        power.broken_barh([(t, 1) for t in missing], (0, 1), transform=power.get_xaxis_transform(), zorder=0.5,
                          facecolor="none", edgecolor=MISSING, hatch="///", lw=0,
                          label=_MISSING_LABEL if len(missing) else None)
    for sender, t in zip(places["sender"], places["t"]):
        if sender in agents:
            power_axes[agents.index(sender)].axvline(t, color=RESTART, lw=1.5, ls="--", zorder=4,
                                                     label="process restarted (the agent)")
    totals_ax = fig.add_subplot(grid[0, 1])
    if len(start) == 1:
        _bill(totals_ax, days, agents)
    else:
        _daily_totals(totals_ax, days, list(start), agents)
    return price_ax, [price_ax, *power_axes, *money_axes[:-1], power_axes[-1], money_axes[-1]], grid


def _compact(fig, hours, meter, days, agents, start, places, below):
    """More agents: the price and, beside it, the bills ranked; below, agents x hours heat maps of the deviation and,
    beside it on the same rows, of the penalty (compact.py). Returns the price's axes, every axes on the time axis
    and the grid, whose last rows, of heights ``below`` (inches), are left for the caller."""
    height, span = maps_height(len(agents)), 24 * len(start)
    grid = fig.add_gridspec(2 + len(below), 2, width_ratios=(3, 2), height_ratios=(TOP_IN, height, *below))
    price_ax = fig.add_subplot(grid[0, 0])
    deviation_ax = fig.add_subplot(grid[1, 0], sharex=price_ax)
    penalty_ax = fig.add_subplot(grid[1, 1], sharey=deviation_ax)
    colour_bar(fig, deviation_map(deviation_ax, hours, agents, span), deviation_ax, "MWh")
    credit = bool((hours["deviation_credit"] != 0).any())
    colour_bar(fig, penalty_map(penalty_ax, hours, agents, span, credit), penalty_ax, "$", dollars=True)
    agent_axis(deviation_ax, agents, height)
    penalty_ax.tick_params(axis="y", labelleft=False)
    per = penalty_hours(len(start))
    for ax in (deviation_ax, penalty_ax):
        mark_missing(ax, hours, agents, _MISSING_LABEL, per=per if ax is penalty_ax else 1)
    mark_restarts(deviation_ax, places, agents, "process restarted (the agent)")
    for t in places.loc[~places["sender"].isin(agents), "t"]:  # the DMO's: every agent's row
        deviation_ax.axvline(t, color=RESTART, lw=1.5, ls="--", zorder=4, label=_DMO_RESTARTED)
    ranked_bills(fig.add_subplot(grid[0, 1]), days, agents, len(start))
    return price_ax, [price_ax, deviation_ax, *([penalty_ax] if per == 1 else [])], grid


def _price(ax, hours: pd.DataFrame, on_feeder: bool) -> None:
    """The clearing price per hour, congested hours marked as the clearing decided."""
    per_hour = hours.drop_duplicates(["market_day", "hour"]).sort_values("t")
    # on a feeder every bus has its price (the heat map below): the one common to all is the substation's
    price = "energy_price_per_mwh" if on_feeder else "clearing_price_per_mwh"
    _hourly_stairs(ax, per_hour, price, color=_AWARD)
    for where, marker in (("import", "^"), ("export", "v"), ("line", "s"), ("voltage", "D")):
        congested = per_hour[(per_hour["congestion"] == where).fillna(False)]  # <NA>: not stated, not marked
        if not congested.empty:
            ax.plot(congested["t"] + 0.5, congested[price], marker, color=PENALTY, ms=5,
                    ls="none", label=f"{where} {'limit binds' if where in ('line', 'voltage') else 'congestion'}"
                                     " (as the clearing decided)")
    ax.set_ylabel("$/MWh")
    ax.set_title("the substation's price per hour" if on_feeder else "clearing price per hour", loc="left",
                 fontsize=10)


def _missing(hours: pd.DataFrame, meter: pd.DataFrame) -> np.ndarray:
    """Per line of ``hours``: no accepted meter report for the hour, or a sub-period of it settled as missing."""
    reported = meter[["agent", "market_day", "hour"]].drop_duplicates().assign(reported=True)
    merged = hours[["agent", "market_day", "hour"]].merge(reported, on=["agent", "market_day", "hour"], how="left")
    return merged["reported"].isna().to_numpy() | (hours["missing_subperiods"] > 0).to_numpy()


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
    ax.bar(middle, hours["deviation_penalty"], width=0.8, color=PENALTY, label="deviation penalty")
    if credit:
        ax.bar(middle, -hours["deviation_credit"], width=0.8, color=CREDIT, label="deviation credit (drawn below 0)")
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_ylabel("$")
    ax.yaxis.set_major_formatter(DOLLARS)
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
    ax.set_xticks(range(0, span, 24 * every), [f"0\n{d}" for d in short_dates(market_days)[::every]])
    ax.xaxis.set_minor_locator(MultipleLocator(6 if len(market_days) <= 4 else 12))
    ax.xaxis.set_minor_formatter(FuncFormatter(lambda x, _: f"{x % 24:.0f}" if x % 24 else ""))
    ax.tick_params(axis="x", which="minor", labelsize=7)
    for boundary in range(24, span, 24):
        ax.axvline(boundary, color="0.4", lw=0.8, ls=":")


def _bill(ax, days: pd.DataFrame, agents: list[str]) -> None:
    """One day's bill per agent, $: energy charge and deviation penalty stacked (a negative energy charge, an
    export paid for, below 0), the credit below 0, the total marked and written above."""
    bill = days.set_index("agent").reindex(agents)
    x = np.arange(len(agents))
    parts, up, down = stacked(bill)
    for label, values, base, color in parts:
        ax.bar(x, values, bottom=base, width=0.6, color=color, label=label)
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
    ax.yaxis.set_major_formatter(DOLLARS)
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
    ax.set_xticks(x[::every], short_dates(market_days)[::every])
    ax.set_xlim(-0.5, len(market_days) - 0.5)
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_xlabel("market day")
    ax.set_ylabel("$")
    ax.yaxis.set_major_formatter(DOLLARS)
    ax.grid(alpha=0.3)
    ax.set_title("daily total per agent (what it owes)", loc="left", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)  # beside: covers no point
