"""The day-ahead clearing: the copper plate against the network clearing on the IEEE 33-bus and a 1000-bus feeder,
with the operating envelopes and the AC check of each feeder's day, and the AC-faithful clearing beside the one-shot
LinDistFlow clearing.

One market day of N agents with three bid steps per agent-hour (a book built from a seed, the same for every case),
cleared by ``dmo.market.clearing.clear`` (the copper plate) and ``dmo.market.distflow.clear_network`` on each
feeder, each a few times in this process; the median wall time is the figure (the machine is shared: the spread is
reported too). Each case says how its hours cleared (the congestion labels), so a figure is read with the work it
did: an hour the copper plate clears costs a check of its flows, an hour with a binding line or voltage an LP.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections import Counter

import numpy as np

from dmo.market.clearing import BidCurve, Step, clear
from dmo.market.acflow import check_hours
from dmo.market.distflow import clear_network
from dmo.market.envelope import operating_envelope
from dmo.operator.feeder import per_bus
from scenarios.horizon import HOURS
from scenarios.network import Network, load_network, synthetic

from ..arguments import positive_int

STEPS_PER_HOUR = 3
GOAL_S = {"ieee33": 0.2, "synthetic1000": 1.0}  # a day of 100 agents (docs/benchmarks.md)
AC_GOAL_S = {"ieee33": 1.5, "synthetic1000": 6.0}  # the AC check of that day's 24 hours
ENVELOPE_GOAL_S = 0.5  # the operating envelopes of that day, on either feeder
AC_FAITHFUL_GOAL = 3.0  # the AC-faithful clearing's time over the one-shot clearing's, on either feeder
# An hour "breaks" the feeder when its plan's AC flow is this far outside a voltage limit (p.u.) or over a rating
BROKEN_PU, BROKEN_LOADING = 1e-4, 0.005


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", type=positive_int, default=100, help="agents bidding (default: 100)")
    parser.add_argument("--repeats", type=positive_int, default=5, help="clearings timed per case (default: 5)")
    parser.add_argument("--buses", type=positive_int, default=1000,
                        help="buses of the synthetic feeder (default: 1000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the bids and the agents' buses (default: 0)")


def market_day(network: Network, agents: int, seed: int) -> tuple[list[BidCurve], dict[str, str], list[float], float]:
    """A day's book on ``network``: each agent at a random bus (not the substation) buys two blocks and sells one
    every hour, each block about the feeder's nominal fixed load over the number of agents; the ISO price (24) and
    a substation limit of 1.5 times the nominal fixed load, each way."""
    rng = np.random.default_rng([seed, agents, network.n_buses])
    feeder = [b for b in network.buses if b != network.substation]
    block = float(network.load_p_mw.sum()) / agents
    buses = {f"mg{i:04d}": feeder[int(rng.integers(len(feeder)))] for i in range(agents)}
    prices = rng.uniform([[[60.0, 30.0, 20.0]]], [[[120.0, 60.0, 80.0]]], (agents, HOURS, STEPS_PER_HOUR)).round(2)
    sizes = block * rng.uniform([[[0.3, 0.3, -0.6]]], [[[0.9, 0.9, -0.2]]], (agents, HOURS, STEPS_PER_HOUR)).round(3)
    bids = [BidCurve(a, tuple(tuple(Step(float(p), float(q)) for p, q in zip(prices[i, h], sizes[i, h]))
                              for h in range(HOURS))) for i, a in enumerate(buses)]
    iso = [round(45 + 15 * np.sin(2 * np.pi * (h - 8) / HOURS), 2) for h in range(HOURS)]
    return bids, buses, iso, 1.5 * float(network.load_p_mw.sum())


def _timed(call, repeats: int) -> tuple[dict, object]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = call()
        times.append(time.perf_counter() - start)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times)}, result


def run(args) -> dict:
    rows, faithful = [], []
    # One row per feeder: its clearing, and the AC power-flow check of the day it cleared (24 hours).
    for network in (load_network("ieee33"), synthetic(args.buses)):
        bids, buses, iso, limit = market_day(network, args.agents, args.seed)
        if not rows:  # the copper plate clears the first feeder's book: the same bids, no network
            figures, plate = _timed(lambda: clear(bids, iso, limit, limit), args.repeats)
            rows.append({"case": "copper plate", "buses": 1, **figures, **_labels(plate.congested), "shed_mw": 0.0})
        figures, cleared = _timed(lambda: clear_network(bids, network, buses, iso, limit, limit), args.repeats)
        injection = per_bus(network, buses, cleared.awards) - cleared.shed_mw
        ac, checks = _timed(lambda: check_hours(network, injection), args.repeats)
        envelope, rooms = _timed(lambda: operating_envelope(cleared, network, buses, limit, limit), args.repeats)
        at = [network.index[b] for b in set(buses.values())]
        rows.append({"case": network.name, "buses": network.n_buses, **figures, **_labels(cleared.congested),
                     "shed_mw": float(cleared.shed_mw.sum()), "ac_median_s": ac["median_s"],
                     "ac_max_s": ac["max_s"], "ac_converged": sum(c.converged for c in checks),
                     "ac_voltage_error_pu": max(c.voltage_error_pu for c in checks),
                     "envelope_median_s": envelope["median_s"], "envelope_max_s": envelope["max_s"],
                     **{f"{way}_room_{k}": v for way, room in (("import", rooms.import_mw), ("export", rooms.export_mw))
                        for k, v in (("mean_mw", float(room[:, at].mean())),
                                     ("zero_share", float((room[:, at] == 0).mean())))}})
        timed, ac_cleared = _timed(lambda: clear_network(bids, network, buses, iso, limit, limit, method="ac"),
                                   args.repeats)
        faithful.append(_faithful(network.name, figures, cleared, timed, ac_cleared))
    for row in rows:
        row["over_copper_plate"] = row["median_s"] / rows[0]["median_s"]
    over = {row["case"]: row["over_one_shot"] for row in faithful}
    goal = {row["case"]: {"goal_s": GOAL_S[row["case"]], "met": row["median_s"] <= GOAL_S[row["case"]],
                          "ac_goal_s": AC_GOAL_S[row["case"]], "ac_met": row["ac_median_s"] <= AC_GOAL_S[row["case"]],
                          "envelope_goal_s": ENVELOPE_GOAL_S,
                          "envelope_met": row["envelope_median_s"] <= ENVELOPE_GOAL_S,
                          "ac_faithful_goal": AC_FAITHFUL_GOAL,
                          "ac_faithful_met": over[row["case"]] <= AC_FAITHFUL_GOAL}
            for row in rows if row["case"] in GOAL_S and args.agents == 100}
    return {"agents": args.agents, "steps": args.agents * HOURS * STEPS_PER_HOUR, "repeats": args.repeats,
            "rows": rows, "ac_faithful": faithful, "goal": goal}


def _faithful(case: str, one_shot: dict, cleared, timed: dict, ac) -> dict:
    """A feeder's AC-faithful clearing beside its one-shot one: times, iterations, and per method how many hours'
    plans break the feeder in AC and by how much at worst."""
    out = {"case": case, "one_shot_median_s": one_shot["median_s"], "median_s": timed["median_s"],
           "over_one_shot": timed["median_s"] / one_shot["median_s"],
           "iterations_mean": float(np.mean(ac.iterations)), "iterations_max": max(ac.iterations)}
    for name, result in (("one_shot", cleared), ("ac", ac)):
        excess, overload = np.array(result.ac_voltage_excess_pu), np.array(result.ac_overload)
        out[f"{name}_hours_broken"] = int(((excess > BROKEN_PU) | (overload > BROKEN_LOADING)).sum())
        out[f"{name}_voltage_excess_pu"] = float(excess.max())
        out[f"{name}_overload"] = float(overload.max())
    out["loss_price_mean"] = float(ac.loss.mean())
    return out


def _labels(congested) -> dict:
    """How many of the day's hours each congestion label took."""
    count = Counter(congested)
    return {f"hours_{label}": count[label] for label in ("none", "import", "export", "line", "voltage")}
