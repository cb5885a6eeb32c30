"""Fleets of hundreds of agents on one machine: memory per agent, start-up, the day's wall time, the share of it
spent solving, the overhead, and whether every statement re-settles identically from the recording.

For each N, one ``dmosim run --agents N --hosting H --per-process K`` of small agents (1 scenario, hourly), recording
on. While it runs, the proportional set size (PSS: each shared page counted once over the processes sharing it) of
every process of the run (the launcher, the DMO, the recorder, the agents' host and the agents) is summed about every
``INTERVAL_S`` seconds; the largest sum is the run's memory. The day is split as ``dmosim bench day`` splits it
(``split_day``): the agents' critical-path computation and the overhead. Whether the recording re-settles to the
statements the DMO published is the run's own check (``recorded.resettled`` of its result). Definitions in
docs/benchmarks.md, "fleet".
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shutil
import tempfile
import threading
from pathlib import Path

from messages.transport.credentials import MAX_HOSTS

from ..arguments import gap, integer, nonneg_float, positive_int
from ..experiment.spec import HOSTINGS, MAX_AGENTS
from ..launch.processes import descendants
from .day import GOAL_PCT, run_and_read, split_day

INTERVAL_S = 1.0  # how often the run's memory is summed
GOAL_AGENTS = 200  # the goals below hold for this fleet (issue 27)
GOAL_GIB = 8.0     # every process of the run together
GOAL_WALL_S = 600.0  # the whole run, start-up and tables included
GOAL_PHASE_S = 5.0  # registration, and clearing


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", type=integer(1, MAX_AGENTS), nargs="+", default=[50, 100, GOAL_AGENTS],
                        metavar="N", help=f"fleet sizes, one day each (default: 50 100 {GOAL_AGENTS})")
    parser.add_argument("--hosting", choices=HOSTINGS, default="fork", help="how the agents start (default: fork)")
    parser.add_argument("--per-process", type=positive_int, default=10, metavar="K",
                        help="agents per forked process (default: 10; 1 with --hosting process)")
    parser.add_argument("--routers", type=integer(0, MAX_HOSTS), default=0, metavar="N",
                        help="Zenoh routers the run starts, as dmosim run --routers (default: 0, the DMO is the router)")
    parser.add_argument("--scenarios", type=positive_int, default=1, help="scenarios per agent schedule (default: 1)")
    parser.add_argument("--subperiods", type=positive_int, default=1, help="sub-periods per hour (default: 1)")
    parser.add_argument("--gap", type=gap, default=0.05, help="relative MIP gap of the schedules (default: 0.05)")
    parser.add_argument("--timeout", type=nonneg_float, default=3600.0,
                        help="seconds one day may take before the bench stops it (default: 3600)")
    parser.add_argument("--out", metavar="DIR", help="keep each run's directory here, as DIR/agents-N (default: "
                                                     "scratch directories, removed)")


def run(args) -> dict:
    per_process = args.per_process if args.hosting == "fork" else 1
    cores = os.cpu_count() or 1
    rows = []
    for n in args.agents:
        keep = Path(args.out) / f"agents-{n}" if args.out else Path(tempfile.mkdtemp(prefix="dmosim-fleet-"))
        try:
            rows.append(_one_fleet(args, n, per_process, keep, cores))
        finally:
            if not args.out:
                shutil.rmtree(keep, ignore_errors=True)
    return {
        "setup": {"agents": "the fleet of dmosim run: the paper's microgrid, scaled and shifted",
                  "hosting": args.hosting, "per_process": per_process, "routers": args.routers,
                  "scenarios": args.scenarios,
                  "subperiods": args.subperiods, "gap": args.gap, "recording": "on",
                  "memory": f"the largest sum of every process's PSS, sampled every {INTERVAL_S:g} s",
                  "machine": f"{cores} cores shared with other work: one run per N, noisy"},
        "fleets": rows,
        "goal": next((_goal(row) for row in rows if row["agents"] == GOAL_AGENTS), {}),
    }


def _goal(row: dict) -> dict:
    """The goals for a fleet of ``GOAL_AGENTS``, judged on its row."""
    return {"agents": row["agents"], "total_gib": row["total_gib"], "total_target_gib": GOAL_GIB,
            "wall_s": row["wall_s"], "wall_target_s": GOAL_WALL_S,
            "overhead_pct": row["overhead_pct"], "overhead_target_pct": GOAL_PCT,
            "registration_s": row["registration_s"], "clearing_s": row["clearing_s"],
            "phase_target_s": GOAL_PHASE_S, "resettled_identically": row["resettled_identically"],
            "incidents": row["incidents"], "verdict_ok": row["verdict_ok"],
            "met": row["total_gib"] < GOAL_GIB and row["incidents"] == 0
            and row["wall_s"] < GOAL_WALL_S and row["overhead_pct"] < GOAL_PCT
            and max(row["registration_s"], row["clearing_s"]) < GOAL_PHASE_S
            and row["resettled_identically"] and row["verdict_ok"]}


def _one_fleet(args, n: int, per_process: int, keep: Path, cores: int) -> dict:
    flags = ["--agents", str(n), "--scenarios", str(args.scenarios), "--subperiods", str(args.subperiods),
             "--gap", repr(args.gap), "--hosting", args.hosting, "--per-process", str(per_process),
             "--routers", str(args.routers)]
    memory = TreeMemory()
    day = run_and_read(flags, args.timeout, keep=keep, watch=memory.watching)
    result = day["result"]
    split = split_day(result.phase_s, day["compute"], cores)["totals"]
    again = result.recorded.resettled
    differences = again.differences or ([again.error] if again.error else [])
    others = {role: round(mib, 1) for role, mib in memory.peak_by_role.items() if role != "agents"}
    return {"agents": n, "total_gib": round(memory.peak_mib / 1024, 2),
            "per_agent_mib": round(memory.peak_mib / n, 1),
            "agents_mib": round(memory.peak_by_role.get("agents", 0.0), 1), **others,
            "registration_s": round(result.phase_s["registration"], 2),
            "clearing_s": round(result.phase_s.get("clearing", 0.0), 3),
            "day_s": round(split["day_s"], 1), "wall_s": round(day["process_s"], 1),
            "solving_pct": round(100.0 * split["compute_s"] / split["day_s"], 1) if split["day_s"] else None,
            "overhead_pct": round(split["overhead_pct"], 2), "cpu_wait_s": round(split["cpu_wait_s"], 1),
            "incidents": len(result.incidents), "resettled_identically": again.identical,
            **({"differences": "; ".join(differences[:3])} if differences else {}),
            "verdict_ok": result.verdict.ok}


class TreeMemory:
    """The largest sum of PSS over a process and all its descendants while ``watching`` it, and each kind of role's
    share of that sum (``peak_by_role``: run, dmo, recorder, host, agents)."""

    def __init__(self, interval_s: float = INTERVAL_S):
        self.interval_s = interval_s
        self.peak_mib = 0.0
        self.peak_by_role: dict[str, float] = {}

    @contextlib.contextmanager
    def watching(self, pid: int):
        stop = threading.Event()
        thread = threading.Thread(target=self._sample, args=(pid, stop), name="fleet-memory", daemon=True)
        thread.start()
        try:
            yield self
        finally:
            stop.set()
            thread.join()

    def _sample(self, root: int, stop: threading.Event) -> None:
        while not stop.wait(self.interval_s):
            by_role: dict[str, float] = {}
            for pid, parent in descendants(root):
                mib = pss_mib(pid)
                if mib is not None:
                    role = role_of(pid, parent, root)
                    by_role[role] = by_role.get(role, 0.0) + mib
            total = sum(by_role.values())
            if total > self.peak_mib:
                self.peak_mib, self.peak_by_role = total, by_role


def pss_mib(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            found = re.search(r"^Pss:\s+(\d+) kB", f.read(), re.M)
    except OSError:
        return None
    return int(found.group(1)) / 1024 if found else None


def role_of(pid: int, parent: int, root: int) -> str:
    """What a process of the run is, from its command line: the launcher (``run``), ``dmo``, ``recorder``, the
    agents' ``host``, or ``agents`` (a process of its own, or forked from the host)."""
    if pid == root:
        return "run"
    try:
        with open(f"/proc/{pid}/cmdline") as f:
            argv = f.read().split("\0")
    except OSError:
        return "agents"
    if any(a.endswith("dmosim.launch.host") for a in argv):
        return "agents" if parent != root else "host"
    for verb, role in (("dmo", "dmo"), ("record", "recorder")):
        if verb in argv[:4]:
            return role
    return "agents"
