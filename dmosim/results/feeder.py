"""The feeder's panels of a run's figure (``dmosim plot``, ``run.png``) on a feeder: the price of every bus in every
hour as a heat map on the run's time axis, load shed and generation spilled marked on it; and, at the hour
``shown_hour`` picks, the voltage along each branch of the feeder and each line's loading as the clearing limits it,
with what binds marked."""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Sequence

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.colors import TwoSlopeNorm
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

_PLAN, _REALISED, _BINDING, _LIMIT, _SHOWN = "#1f77b4", "#ff7f0e", "#d62728", "0.25", "#17becf"
_SHED, _SPILLED = "white", "#2ca02c"
HEAT_IN, LOADING_IN = 3.2, 2.5  # the feeder's two rows: the heat map and the voltage beside it; the loading below
MAX_BARS = 48  # a larger feeder's loading panel shows its MAX_BARS most loaded lines, so each stays legible
EPS = 1e-6  # MW of shed or spilled power, or $/MWh of a price component, below which there is none


def parents(buses: Sequence[str], lines: Sequence[str]) -> dict[str, str]:
    """Each bus's parent, by name: the ``from`` of the line whose ``to`` it is (lines are named "from-to" from the
    substation's side). A bus name may hold a "-", so a line is split where both sides name buses of ``buses``."""
    known, parent = set(buses), {}
    for line in lines:
        splits = [(line[:i], line[i + 1:]) for i, c in enumerate(line)
                  if c == "-" and line[:i] in known and line[i + 1:] in known]
        if len(splits) != 1:
            raise ValueError(f"line {line!r} does not name two buses of the feeder in one way")
        parent[splits[0][1]] = splits[0][0]
    return parent


def branches(buses: Sequence[str], lines: Sequence[str]) -> list[list[str]]:
    """The feeder as paths away from the substation, each from its junction (the bus it leaves; none for the first,
    which starts at the substation) to a far end, so that a voltage profile drawn path by path joins no two laterals:
    at each bus a path goes on along the child with the deepest subtree beneath it (the first in line order among
    equals), and each other child starts a path of its own. Every line is two consecutive buses of exactly one path.
    The first path is the feeder's longest, then each lateral after the path it leaves, nearest the substation
    first."""
    parent = parents(buses, lines)
    children: dict[str, list[str]] = {b: [] for b in buses}
    for child, p in parent.items():  # in line order
        children[p].append(child)
    order = [b for b in buses if b not in parent]  # the substation: the one bus no line feeds
    for b in order:  # breadth first: each bus after its parent
        order.extend(children[b])
    height = {}
    for b in reversed(order):
        height[b] = 1 + max((height[c] for c in children[b]), default=0)
    paths, starts = [], deque([[order[0]]])
    while starts:
        path = starts.popleft()
        while children[path[-1]]:
            here = path[-1]
            heir = max(children[here], key=height.__getitem__)  # max keeps the first of equals
            starts.extend([here, c] for c in children[here] if c != heir)
            path.append(heir)
        paths.append(path)
    return paths


def depths(buses: Sequence[str], lines: Sequence[str]) -> dict[str, int]:
    """Each bus's distance from the substation, in lines."""
    parent, depth = parents(buses, lines), {}
    for b in buses:
        chain = [b]
        while chain[-1] not in depth and chain[-1] in parent:
            chain.append(parent[chain[-1]])
        base = depth.get(chain[-1], 0)
        for k, c in enumerate(reversed(chain)):
            depth.setdefault(c, base + k)
    return depth


def shown_hour(network: pd.DataFrame, buses: pd.DataFrame) -> tuple[str, int, str]:
    """(market day, hour, why) of the hour the voltage and loading panels show, the first of equals:
    - where the feeder's limits move a bus's price most: the largest |congestion + voltage component| of any bus
      ("most congested"), when one is not 0. It counts line and voltage limits in one unit, $/MWh, where the
      lines' shadow prices ($/h per MW) and the buses' ($/h per p.u.) could not be added; a bus shedding load or
      spilling generation behind a limit has its price set by them, so such hours come first;
    - else, when load is shed or generation spilled (at the substation's own limit, say), the hour with the most
      MW of both ("most shed and spilled");
    - else the plan's largest import at the substation ("peak import"): where the feeder is most stressed."""
    plan = network[network["stage"] == "plan"].reset_index(drop=True)
    at = ["market_day", "hour"]
    prices = buses[buses["stage"] == "plan"]
    local = (prices["congestion_price_per_mwh"].astype("Float64").fillna(0)
             + prices["voltage_price_per_mwh"].astype("Float64").fillna(0)).abs()
    cost = local.groupby([prices["market_day"], prices["hour"]]).max().reindex(
        pd.MultiIndex.from_frame(plan[at])).fillna(0).to_numpy(dtype=float)
    curtailed = (plan["shed_mw"].astype("Float64").fillna(0)
                 + plan["spilled_mw"].astype("Float64").fillna(0)).to_numpy(dtype=float)
    if cost.max() > EPS:
        row, why = plan.loc[int(np.argmax(cost))], "most congested"
    elif curtailed.max() > EPS:
        row, why = plan.loc[int(np.argmax(curtailed))], "most shed and spilled"
    else:
        row, why = plan.loc[int(np.argmax(plan["substation_mw"].to_numpy(dtype=float)))], "peak import"
    return row["market_day"], int(row["hour"]), why


def voltage_limits(rec) -> tuple[float, float] | None:
    """(v_min, v_max), p.u., of the run's feeder when its recording names a built-in one (``[network] feeder``) whose
    buses but the substation share them; None otherwise. The recorded messages carry no limits, and a feeder file
    the recording names is not read (docs/network.md, "A feeder in an experiment")."""
    from scenarios.network import NETWORKS, load_network  # noqa: PLC0415  (ieee33 imports pandapower: 1 s)

    try:
        feeder = ((json.loads(rec.metadata.get("config") or "{}") or {}).get("network") or {}).get("feeder")
    except (ValueError, AttributeError):
        return None
    if not isinstance(feeder, str) or feeder not in NETWORKS:
        return None
    network = load_network(feeder)
    others = np.arange(len(network.buses)) != network.root  # the substation is held at its own voltage
    low, high = np.unique(network.v_min[others]), np.unique(network.v_max[others])
    return (float(low[0]), float(high[0])) if len(low) == len(high) == 1 else None


def draw(fig, cells, frames: dict[str, pd.DataFrame], start: dict[str, int], time_ax,
         limits: tuple[float, float] | None = None):
    """The feeder's panels in ``cells`` of ``fig`` (three cells of a grid: the heat map's, in the column of the run's
    time axis, the voltage's beside it, the loading's below both), from the tables' ``network``, ``buses`` and
    ``lines``; the heat map shares its x with ``time_ax``. ``start`` gives each market day's first hour on the time
    axis, ``limits`` the feeder's voltage limits if known (``voltage_limits``). Returns the heat map's axes, for
    the caller to put on the run's time axis."""
    network, buses, lines = frames["network"], frames["buses"], frames["lines"]
    heat_ax = fig.add_subplot(cells[0], sharex=time_ax)
    volt_ax, load_ax = fig.add_subplot(cells[1]), fig.add_subplot(cells[2])
    day, hour, why = shown_hour(network, buses)
    _prices(heat_ax, buses[buses["stage"] == "plan"], start, start[day] + hour - 1)
    at = lambda frame: frame[(frame["market_day"] == day) & (frame["hour"] == hour)]  # noqa: E731
    plan, facts = at(network)[at(network)["stage"] == "plan"], ""
    for column, what in (("shed_mw", "shed"), ("spilled_mw", "spilled")):  # what else the hour did, if anything
        mw = float(plan[column].astype("Float64").fillna(0).sum())
        facts += f"; {mw:.2f} MW {what}" if mw > EPS else ""
    when = f"{day} hour {hour} ({why}"
    _voltages(volt_ax, at(buses), at(network), list(at(lines).drop_duplicates("line")["line"]), limits,
              f"voltage along each branch,\n{when})")
    _loading(load_ax, at(lines), f"{when}{facts})")
    return heat_ax


def _prices(ax, plan: pd.DataFrame, start: dict[str, int], shown: int) -> None:
    """Bus x hour of the run, coloured by the bus's price less the hour's lowest: where, and when, prices separate;
    each bus-hour that sheds load or spills generation marked, the hour the other panels show framed. The colours
    stop at the largest spread of an hour that sheds no load, so that the value of lost load does not wash out the
    rest: a larger spread takes the end colour, and the bar's arrow says so."""
    order = list(dict.fromkeys(plan["bus"]))
    span = 24 * len(start)
    plan = plan.assign(t=plan["market_day"].map(start) + plan["hour"] - 1, row=plan["bus"].map(
        {bus: i for i, bus in enumerate(order)}))
    grid = plan.pivot_table(index="bus", columns="t", values="bus_price_per_mwh").reindex(
        index=order, columns=range(span)).astype(float)
    spread = (grid - grid.min(axis=0)).to_numpy(dtype=float, na_value=np.nan)
    shedding = plan.groupby("t")["shed_mw"].sum().reindex(range(span)).astype(float).fillna(0).to_numpy() > EPS
    calm = spread[:, ~shedding] if np.isfinite(spread[:, ~shedding]).any() else spread
    top = max(float(np.nanmax(calm)) if np.isfinite(calm).any() else 0.0, 1e-9)
    image = ax.imshow(spread, aspect="auto", cmap="magma_r", interpolation="nearest",
                      extent=(0, span, len(order) - 0.5, -0.5), norm=TwoSlopeNorm(vcenter=top / 2, vmin=0, vmax=top))
    for column, marker, color, label in (("shed_mw", "v", _SHED, "load shed (bus, hour)"),
                                         ("spilled_mw", "^", _SPILLED, "generation spilled (bus, hour)")):
        hit = plan[plan[column].astype("Float64").fillna(0) > EPS]
        if not hit.empty:
            ax.plot(hit["t"] + 0.5, hit["row"], marker, color=color, mec="black", mew=0.6, ms=4, ls="none",
                    label=label)
    ax.add_patch(Rectangle((shown, -0.5), 1, len(order), fill=False, edgecolor=_SHOWN, lw=1.5, zorder=3,
                           label="the hour the feeder's panels show"))
    step = label_step(len(order), 12)  # at most 12 bus labels, so 33 (or 1,000) buses stay legible
    ax.set_yticks(range(0, len(order), step), order[::step], fontsize=7)
    ax.set_ylabel("bus (feeder order)")
    ax.set_title("bus price above the hour's lowest, $/MWh", loc="left", fontsize=10)
    over = bool(np.isfinite(spread).any() and np.nanmax(spread) > top)
    bar = ax.figure.colorbar(image, ax=ax, fraction=0.04, pad=0.015, aspect=30, extend="max" if over else "neither")
    bar.ax.tick_params(labelsize=7)


def _voltages(ax, buses: pd.DataFrame, network: pd.DataFrame, lines: list[str],
              limits: tuple[float, float] | None, title: str) -> None:
    """Each bus's voltage (LinDistFlow), planned and realised, against its distance from the substation in lines,
    one polyline per branch (``branches``) so that laterals are not joined to each other; the AC lowest marked, each
    bus the plan holds at a voltage limit marked, and the feeder's limits drawn when known."""
    order = list(dict.fromkeys(buses["bus"]))
    paths, depth = branches(order, lines), depths(order, lines)
    for stage, color, style, z in (("plan", _PLAN, "-", 3), ("realised", _REALISED, "--", 2)):  # the plan on top
        own, ac = buses[buses["stage"] == stage], network[network["stage"] == stage]
        if own.empty:
            continue
        v = dict(zip(own["bus"], own["voltage_pu"].astype(float)))
        segments = [[(depth[b], v[b]) for b in path] for path in paths if len(path) > 1]
        ax.add_collection(LineCollection(segments, colors=color, lw=1.1, linestyles=style, zorder=z,
                                         label=f"{stage} (LinDistFlow)"))
        ax.plot([depth[b] for b in order], [v[b] for b in order], ".", color=color, ms=3 if len(order) <= 100 else 1.5,
                zorder=z)
        lowest = ac["ac_v_min_bus"].iloc[0] if not ac.empty else None
        if lowest in depth:  # an hour with no AC solution names no bus
            ax.plot(depth[lowest], ac["ac_v_min_pu"].iloc[0], "x", color=color, ms=7, label=f"{stage}: AC lowest")
    plan = buses[buses["stage"] == "plan"]
    for side, marker in (("v_min", "v"), ("v_max", "^")):
        held = plan[(plan["binding_voltage"] == side).fillna(False)]
        if not held.empty:
            ax.plot(held["bus"].map(depth), held["voltage_pu"].astype(float), marker, color=_BINDING, ms=6,
                    mfc="none", mew=1.2, ls="none", label=f"held at {side} (plan)")
    if limits is not None:
        margin = network.loc[network["stage"] == "plan", "ac_margin"].astype("Float64").fillna(0)
        margin = float(margin.iloc[0]) if len(margin) else 0.0
        for k, limit in enumerate(limits):
            ax.axhline(limit, color=_LIMIT, lw=1, ls="--", label=None if k else "v_min, v_max (feeder)")
            if margin > 0:
                ax.axhline(limit + margin * (1 - 2 * k), color=_LIMIT, lw=0.8, ls=":",
                           label=None if k else f"less the clearing's margin ({margin:g} p.u.)")
    if len(paths) <= 8:  # name each branch's far end, where there are few enough to read
        v = dict(zip(plan["bus"], plan["voltage_pu"].astype(float))) if not plan.empty else {}
        for path in paths:
            if path[-1] in v:
                ax.annotate(path[-1], (depth[path[-1]], v[path[-1]]), xytext=(3, 0), textcoords="offset points",
                            fontsize=7, color="0.3", va="center")
    ax.autoscale_view()
    ax.set_xlim(-0.5, max(depth.values()) * 1.08 + 0.5)  # room for the far ends' names
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.tick_params(labelsize=8)
    ax.set_xlabel("distance from the substation, lines")
    ax.set_ylabel("V, p.u.")
    ax.set_title(title, loc="left", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best", framealpha=0.8)


def _loading(ax, lines: pd.DataFrame, when: str) -> None:
    """Each line's loading as the plan's clearing limits it (``limit_loading``: its largest octagon facet over the
    rating, 1 where it binds; a recording before protocol version 11 has only |S| over the rating), binding lines in
    red with the largest shadow price written, against the limit 1. The realised flow was cleared by no one, so it
    has no facet that limits it: it is drawn as a tick at its |S| over the rating (LinDistFlow) on the plan's bar,
    not as a bar of its own, which beside the plan's would read as a lower loading what is only the octagon's
    0.92-0.96 of the circle. A feeder of more than ``MAX_BARS`` lines shows its ``MAX_BARS`` most loaded."""
    plan = lines[lines["stage"] == "plan"].reset_index(drop=True)
    real = lines[lines["stage"] == "realised"].set_index("line")["loading"]
    faceted = plan["limit_loading"].notna().any() if "limit_loading" in plan else False
    shown = plan["limit_loading"].astype(float) if faceted else plan["loading"].astype(float)
    binding = plan["binding_facet"].notna().to_numpy() if "binding_facet" in plan else np.zeros(len(plan), bool)
    total, keep = len(plan), np.arange(len(plan))
    if total > MAX_BARS:  # binding lines first, then the most loaded; drawn in feeder order
        rank = np.lexsort((-shown.to_numpy(), ~binding))
        keep = np.sort(rank[:MAX_BARS])
    plan, shown, binding = plan.iloc[keep], shown.iloc[keep].to_numpy(), binding[keep]
    x = np.arange(len(plan))
    ax.bar(x[~binding], shown[~binding], 0.7, color=_PLAN, label="plan" + (", as the clearing limits it" if faceted
                                                                            else " (|S| / rating)"))
    if binding.any():
        ax.bar(x[binding], shown[binding], 0.7, color=_BINDING, edgecolor="black", lw=0.6,
               label="plan: binding (a facet at its bound)")
        prices = plan["line_shadow_price_per_mwh"].astype(float).to_numpy()
        i = int(np.nanargmax(np.where(binding, prices, -np.inf)))
        ax.annotate(f"${prices[i]:,.2f}/h per MW", (x[i], shown[i]), xytext=(0, 3), textcoords="offset points",
                    ha="center", va="bottom", fontsize=7, color=_BINDING,
                    bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 1})
    realised = plan["line"].map(real).to_numpy(dtype=float)
    if np.isfinite(realised).any():
        ax.plot(x, realised, "_", color=_REALISED, ms=float(np.clip(300 / max(len(x), 1), 4, 12)), mew=2, ls="none",
                label="realised |S| / rating (LinDistFlow)")
    ax.axhline(1.0, color=_LIMIT, lw=1, ls="--", label="limit")
    step = label_step(len(plan), MAX_BARS)
    ax.set_xticks(x[::step], list(plan["line"])[::step], fontsize=7, rotation=90)
    ax.set_xlim(-0.6, len(plan) - 0.4)
    top = max(1.0, float(np.nanmax(shown)) if len(shown) else 1.0, float(np.nanmax(realised)) if
              np.isfinite(realised).any() else 1.0)
    ax.set_ylim(0, 1.3 * top)  # room for the legend above the limit
    ax.set_ylabel("largest facet / rating" if faceted else "|S| / rating (LinDistFlow)", fontsize=9)
    which = f" (the {len(plan)} most loaded of {total} lines)" if total > len(plan) else ""
    ax.set_title(("line loading as the clearing limits it, " if faceted else "line loading, ") + when + which,
                 loc="left", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right", ncol=4, frameon=False)


def label_step(n: int, labels: int) -> int:
    """Every how many ticks to label so that at most ``labels`` labels show."""
    return max(1, -(-n // labels))
