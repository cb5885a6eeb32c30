"""Recovery from lost messages: one experiment run without faults and with a drop of every message on every key.

Two ``dmosim run`` of the same experiment (same seed, so the same forecasts and schedules): fault-free, then with
``--fault drop:**:P`` given to every role, so that each message any process publishes (clock, awards, bids,
schedules, meter reports, receipts, statements) is lost with probability P. Receipts, sending again and asking on
silence (docs/protocol.md, "Receipts and sending again") should make each loss cost about a second instead of the
phase's deadline and change no settlement: the bench prints the ratio of the two wall times, what was lost and
recovered, and every statement line that differs between the two recordings (``replay.reproduce.differences``).
"""

from __future__ import annotations

import argparse
import os

from dmo.replay.reproduce import differences
from messages.recording import read_recording

from ..arguments import nonneg_float
from .day import add_run_flags, bench_root, run_and_read, run_flags

GOAL_RATIO = 1.3  # wall time with drops / without: what a lost message may cost


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_run_flags(parser, agents=5, days=3, scenarios=2, subperiods=6, gap_=0.01)
    parser.add_argument("--drop", type=_probability, default=0.02,
                        help="probability that each published message is lost (default: 0.02)")
    parser.add_argument("--out", metavar="DIR",
                        help="keep both runs in DIR/fault-free and DIR/dropped (default: a scratch directory, removed "
                             "unless a run fails)")
    parser.add_argument("--timeout", type=nonneg_float, default=7200.0,
                        help="seconds each run may take before the bench stops it (default: 7200)")


def _probability(text: str) -> float:
    value = nonneg_float(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"{text}: a probability strictly between 0 and 1")
    return value


def run(args) -> dict:
    flags = run_flags(args)
    with bench_root(args.out, "recovery") as root:
        runs = {name: run_and_read(flags + more, args.timeout, keep=root / name)
                for name, more in (("fault-free", []), ("dropped", ["--fault", f"drop:**:{args.drop!r}"]))}
        changed = differences(*(read_recording(root / name / "recording.mcap") for name in runs))
    rows = [_row(name, run) for name, run in runs.items()]
    ratio = rows[1]["wall_s"] / rows[0]["wall_s"]
    return {
        "setup": {"agents": args.agents, "days": args.days, "scenarios": args.scenarios,
                  "subperiods": args.subperiods, "drop": f"drop:**:{args.drop!r} (every key, every role)",
                  "machine": f"{os.cpu_count() or 1} cores shared with other work: one run each, noisy"},
        "runs": rows,
        "ratios": {"wall dropped / fault-free": round(ratio, 3), "goal": f"<= {GOAL_RATIO}",
                   "statement lines that differ": len(changed)},
        **({"differences": changed[:20]} if changed else {}),
    }


def _row(name: str, run: dict) -> dict:
    """One run's wall time and what was lost and recovered: drops injected by the DMO and by the agents, payloads
    the agents sent again, times they asked the DMO, copies the DMO received again. (A run the DMO's verdict does
    not trust, e.g. with an agent locked out, exits 1 and stops the bench in ``run_and_read``.)"""
    result, messages = run["result"], run["messages"].values()
    dmo_drops = result.transport.get("faults_injected", {}).get("drop", 0)
    return {"run": name, "wall_s": round(run["process_s"], 1),
            "dropped_by_dmo": dmo_drops,
            "dropped_by_agents": sum(m["faults_injected"].get("drop", 0) for m in messages),
            "sent_again": sum(m["sent_again"] for m in messages), "asked": sum(m["asked"] for m in messages),
            "received_again": result.received_again, "rejected": result.rejected_messages}
