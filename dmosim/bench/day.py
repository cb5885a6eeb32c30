"""The wall time of a whole market day as processes, split into the agents' computation and protocol overhead, and
beside it the same day in one process (``--hosting in-process``).

For each N, ``dmosim run --agents N`` runs a day of small agents; the DMO reports the wall time of each phase
(``phase_s``) and each agent reports, after its last meter report of the day, the wall and CPU time of every message
it handled, when it took it up and how long it waited for its turn (the ``compute`` of its ``agent_day`` message,
which the DMO's result gives under ``realised``). The split is ``split_day``: the time in which at least one agent
computed is the agents' computation, and the rest of the day, when none did and the day waited on messages and the
DMO, is the overhead (definition in docs/benchmarks.md). The same day then runs in one process, and ``speedup`` is
the command's wall time as processes over its wall time in one process; ``--experiment FILE`` measures an
experiment file the same two ways (e.g. examples/week.toml), with the same split of its days. ``--agents`` with no N
runs the experiment files alone, and ``--no-in-process`` runs each day as processes only (a long experiment, e.g.
examples/stochastic-day.toml, measured once).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from dmo.operator.report import DmoReport

from ..arguments import gap, nonneg_float, positive_int
from ..console import UsageError, stopping_on_terminate
from ..experiment.spec import HOSTINGS, IN_PROCESS, Agents
from ..launch.processes import COMMAND_STOP_S, Command, dmosim_command, interrupts_held, stop_processes
from ..results.report import RunReport, parse_result

GOAL_PCT = 5.0
# The message an agent handles in each step of the day, and the DMO phase that waits for its answer.
STEP_PHASE = {"call_for_bids": "bidding", "award": "scheduling", "grid_state": "realtime"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", type=positive_int, nargs="*", default=[1, 5, 10], metavar="N",
                        help="fleet sizes, one day each (default: 1 5 10; none: only the --experiment files)")
    parser.add_argument("--scenarios", type=positive_int, default=2, help="scenarios per agent schedule (default: 2)")
    parser.add_argument("--subperiods", type=positive_int, default=1, help="sub-periods per hour (default: 1)")
    parser.add_argument("--gap", type=gap, default=0.01,
                        help="relative MIP gap of the agents' schedules (default: 0.01)")
    parser.add_argument("--time-limit", type=nonneg_float, default=120.0, help="seconds per agent solve (default: 120)")
    parser.add_argument("--timeout", type=nonneg_float, default=1800.0,
                        help="seconds one day may take before the bench stops it (default: 1800)")
    parser.add_argument("--experiment", action="append", default=[], metavar="FILE",
                        help="also run this experiment file, as processes and (unless --no-in-process) in one "
                             "process, side by side (repeatable; e.g. examples/week.toml)")
    parser.add_argument("--in-process", action=argparse.BooleanOptionalAction, default=True,
                        help="also run each day in one process, for speedup (default: yes; --no-in-process: "
                             "as processes only)")


def run(args) -> dict:
    if not args.agents and not args.experiment:
        raise UsageError("--agents: no N and no --experiment FILE: nothing to run")
    cores = os.cpu_count() or 1
    rows, phases, notes, files = [], [], [], []
    for n in args.agents:
        flags = ["--agents", str(n), "--scenarios", str(args.scenarios), "--subperiods", str(args.subperiods),
                 "--gap", repr(args.gap), "--time-limit", repr(args.time_limit), "--no-record"]
        row, split, note = _measured(f"N={n}", flags, args, cores)
        rows.append({"agents": n, **row})
        phases += [{"agents": n, **p} for p in split["phases"]]
        notes += note
    for path in args.experiment:
        row, split, note = _measured(path, [path], args, cores)
        files.append({"experiment": path, **row})
        phases += [{"experiment": path, **p} for p in split["phases"]]
        notes += note
    largest = max(rows, key=lambda r: r["agents"]) if rows else None
    return {
        "setup": {"agents": "paper case, fleet of dmosim run (scaled and shifted copies)",
                  "scenarios": args.scenarios, "subperiods": args.subperiods, "gap": args.gap,
                  "recording": "off (--no-record); experiment files as they say",
                  "speedup": "the command's wall time as processes over its wall time with --hosting in-process",
                  "machine": f"{cores} cores shared with other work: one run per N, noisy; with N > {cores} "
                             f"the agents share {cores} cores, so their compute times include waiting for a core"},
        "days": rows,
        **({"experiments": files} if files else {}),
        "phases": phases,
        "goal": ({"agents": largest["agents"], "overhead_pct": largest["overhead_pct"], "target_pct": GOAL_PCT,
                  "met": largest["overhead_pct"] <= GOAL_PCT} if largest else {}),
        **({"notes": "; ".join(notes)} if notes else {}),
    }


def _measured(label: str, flags: list[str], args, cores: int) -> tuple[dict, dict, list[str]]:
    """One ``dmosim run FLAGS`` as processes (and in one process unless ``--no-in-process``): its row (the
    command's wall time, the split of its days summed over them, ``solving_pct`` the share of the days in which an
    agent computed), the split, and notes on what makes the split or the comparison doubtful."""
    day = run_and_read(flags, args.timeout)
    phase_s: dict[str, float] = {}  # summed over the run's days (a run of several has no phase_s of its own)
    for d in day["result"].days:
        for phase, seconds in d.phase_s.items():
            phase_s[phase] = phase_s.get(phase, 0.0) + seconds
    split = split_day(phase_s, day["compute"], cores)
    incidents = day["result"].incidents
    totals = split["totals"]
    row = {"process_s": day["process_s"], **totals,
           "solving_pct": 100.0 * totals["compute_s"] / totals["day_s"] if totals["day_s"] else float("nan"),
           "stopped_short": len(day["result"].schedules_stopped_short), "incidents": len(incidents)}
    notes = []
    if incidents:
        notes.append(f"{label}: {len(incidents)} incident(s), e.g. {incidents[0].reason}; the split assumes "
                     "every agent answered every step")
    if args.in_process:
        one = run_and_read([*flags, "--hosting", IN_PROCESS], args.timeout)
        same = one["result"].settlement == day["result"].settlement
        row.update(in_process_s=one["process_s"], speedup=day["process_s"] / one["process_s"], same_statements=same)
        if not same:
            notes.append(f"{label}: the statements in one process differ from those of the processes")
    return row, split, notes


def split_day(phase_s: dict[str, float], compute: dict[str, list[dict]], cores: int) -> dict:
    """Split the DMO's phase times into the agents' computation and overhead.

    ``compute`` is agent -> its ``compute`` entries ({kind, hour, wall_s, cpu_s, started_at, turn_s},
    ``agents_reported``). An entry computed from ``started_at + turn_s`` to ``started_at + wall_s``: a phase's
    computation is the time in which at least one agent computed (the union of those intervals), and the rest of its
    wall time, when no agent computed and the day waited on messages and the DMO, is overhead. Entries without
    ``started_at`` (an agent_day older than version 9) count as before: per step, the largest wall time of any agent
    (the critical path). The CPU bound is the least wall time the step's CPU work could take on ``cores`` cores:
    max(largest CPU time, total CPU time / cores), so ``cpu_wait_s`` (computation minus CPU bound) is time the agents
    spent waiting for a core, taken by each other or by other work on the machine (``cpu_s`` is the CPU of the thread
    that handled the message: agents sharing a process each count their own). Registration (the agents' processes
    starting and connecting) is reported as ``startup_s``, outside the day.
    """
    steps: dict[tuple[str, int | None], list[dict]] = {}
    for entries in compute.values():
        for e in entries:
            if e["kind"] in STEP_PHASE:
                steps.setdefault((e["kind"], e["hour"]), []).append(e)
    per_phase = {phase: [0.0, 0.0] for phase in phase_s}
    timed: dict[str, list[tuple[float, float]]] = {}  # phase -> computing intervals, s since the epoch
    for (kind, _), entries in steps.items():
        phase = STEP_PHASE[kind]
        if all(e.get("started_at") is not None for e in entries):
            timed.setdefault(phase, []).extend(
                (e["started_at"] / 1e9 + e.get("turn_s", 0.0), e["started_at"] / 1e9 + e["wall_s"]) for e in entries)
        else:
            per_phase[phase][0] += max(e["wall_s"] for e in entries)
        per_phase[phase][1] += max(max(e["cpu_s"] for e in entries), sum(e["cpu_s"] for e in entries) / cores)
    for phase, intervals in timed.items():
        per_phase[phase][0] += covered(intervals)
    rows = [{"phase": phase, "wall_s": wall, "compute_s": per_phase[phase][0], "overhead_s": wall - per_phase[phase][0],
             "cpu_bound_s": per_phase[phase][1]} for phase, wall in phase_s.items() if phase != "registration"]
    day_s = sum(r["wall_s"] for r in rows)
    compute_s = sum(r["compute_s"] for r in rows)
    cpu_bound_s = sum(r["cpu_bound_s"] for r in rows)
    realtime = next((r for r in rows if r["phase"] == "realtime"), None)
    totals = {
        "startup_s": phase_s.get("registration", 0.0),
        "day_s": day_s,
        "compute_s": compute_s,
        "overhead_s": day_s - compute_s,
        "overhead_pct": 100.0 * (day_s - compute_s) / day_s if day_s else float("nan"),
        "per_hour_ms": 1000.0 * realtime["overhead_s"] / 24 if realtime else float("nan"),
        "agent_cpu_s": sum(e["cpu_s"] for entries in compute.values() for e in entries if e["kind"] in STEP_PHASE),
        "cpu_bound_s": cpu_bound_s,
        "cpu_wait_s": compute_s - cpu_bound_s,
    }
    return {"phases": rows, "totals": totals}


def covered(intervals: list[tuple[float, float]]) -> float:
    """The length of the union of intervals (start, end)."""
    total, reach = 0.0, float("-inf")
    for start, end in sorted(intervals):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total


def add_run_flags(parser: argparse.ArgumentParser, *, agents: int, days: int, scenarios: int, subperiods: int,
                  gap_: float) -> None:
    """The flags of a bench that runs ``dmosim run`` of one fleet over several days (``run_flags`` passes them on)."""
    parser.add_argument("--agents", type=positive_int, default=agents, help=f"agents (default: {agents})")
    parser.add_argument("--days", type=positive_int, default=days, help=f"consecutive market days (default: {days})")
    parser.add_argument("--scenarios", type=positive_int, default=scenarios,
                        help=f"scenarios per agent schedule (default: {scenarios})")
    parser.add_argument("--subperiods", type=positive_int, default=subperiods,
                        help=f"sub-periods per hour (default: {subperiods})")
    parser.add_argument("--gap", type=gap, default=gap_, help=f"relative MIP gap of the schedules (default: {gap_})")
    default = Agents()
    parser.add_argument("--hosting", choices=HOSTINGS, default=default.hosting,
                        help=f"how the agents are hosted, as dmosim run --hosting (default: {default.hosting})")
    parser.add_argument("--per-process", type=positive_int, metavar="K",
                        help="agents per forked process, as dmosim run --per-process (default: as dmosim run's)")


def run_flags(args) -> list[str]:
    """The ``dmosim run`` flags of ``add_run_flags``."""
    return ["--agents", str(args.agents), "--days", str(args.days), "--scenarios", str(args.scenarios),
            "--subperiods", str(args.subperiods), "--gap", repr(args.gap), "--hosting", args.hosting,
            *(("--per-process", str(args.per_process)) if args.per_process is not None else ())]


def failure_line(err: str, limit: int = 600) -> str:
    """The line a failed ``dmosim run`` ends its stderr with (its one-line failure, or its exception's), its middle
    cut where longer than ``limit`` characters, so that both its start and its end are shown."""
    line = (err.strip().splitlines() or ["(nothing on stderr)"])[-1]
    return line if len(line) <= limit else f"{line[:limit - 150]} ... {line[-145:]}"


def _result(out: str) -> RunReport | None:
    """The result ``dmosim run --json`` printed, or None if it printed none."""
    try:
        return parse_result(out, "the run's output")
    except UsageError:
        return None


def agents_reported(result: DmoReport) -> tuple[dict[str, list[dict]], dict[str, dict]]:
    """What each agent reported of its days (``realised`` of the run's result: its ``agent_day`` messages, as the
    DMO received them): its ``compute`` entries of every day, each with its ``day``, and the message counts of its
    last day (its process's, since it started). An agent that reported no day stops the bench."""
    realised = result.realised
    missing = [agent for agent in result.agents if not realised.get(agent)]
    if missing:
        raise RuntimeError(f"no realised day from {', '.join(missing)}: did the agents finish their days?")
    compute = {agent: [{**entry.model_dump(), "day": day.day} for day in realised[agent] for entry in day.compute]
               for agent in result.agents}
    return compute, {agent: realised[agent][-1].messages.model_dump() for agent in result.agents}


@contextlib.contextmanager
def bench_root(out: str | None, name: str) -> Iterator[Path]:
    """The directory a bench's runs go in: ``out`` (the user's ``--out``), kept; else a scratch one, removed when
    the block ends unless a run failed or was stopped (a RuntimeError, which names its directory: it stays)."""
    root = Path(out) if out else Path(tempfile.mkdtemp(prefix=f"dmosim-bench-{name}-"))
    keep = bool(out)
    try:
        yield root
    except RuntimeError:
        keep = True
        raise
    finally:
        if not keep:
            shutil.rmtree(root, ignore_errors=True)


def run_and_read(flags: list[str], timeout_s: float, keep: Path | None = None, watch=None) -> dict:
    """One ``dmosim run FLAGS --json`` into a run directory: ``keep``, or a scratch one removed unless the run
    fails or outlasts ``timeout_s`` (the error names it) and removed too when the bench is interrupted. Its result
    (also of a run whose verdict is not ok, which is said on stderr), each agent's ``compute`` entries and
    ``messages`` counts (``agents_reported``), and the command's wall time. ``watch(pid)``, a context manager, is
    held while the command runs (e.g. to sample its memory)."""
    rundir = keep or Path(tempfile.mkdtemp(prefix="dmosim-bench-"))
    argv = dmosim_command("run", *flags, "--registration-timeout", "300", "--bid-timeout", "600",
                          "--schedule-timeout", "600", "--hour-timeout", "120", "--out", str(rundir), "--overwrite",
                          "--json", "--quiet")
    start = time.perf_counter()
    # Its own process group, so that stopping it is our decision: SIGTERM makes dmosim run stop every role it started,
    # and a bench terminated meanwhile stops it so (it would go on in its group).
    with stopping_on_terminate():
        command = None
        try:
            with interrupts_held():  # recorded before a Ctrl-C can leave it running unseen
                command = Command(argv)
            with watch(command.pid) if watch else contextlib.nullcontext():
                code = command.wait(timeout_s)
        except BaseException as exc:
            if command is not None:
                stop_processes([command.process], COMMAND_STOP_S)
            if isinstance(exc, subprocess.TimeoutExpired):  # its logs say where it stood
                raise RuntimeError(f"dmosim run {' '.join(flags)} took over {timeout_s:g} s and was stopped "
                                   f"(run directory: {rundir})") from None
            if keep is None:  # interrupted: nothing of it is wanted
                shutil.rmtree(rundir, ignore_errors=True)
            raise
    process_s = time.perf_counter() - start
    out, err = command.output()
    result = _result(out) if code in (0, 1) else None  # 1: it ran, but its verdict is not ok
    if result is None:
        raise RuntimeError(f"dmosim run {' '.join(flags)} exited {code}: {failure_line(err)} "
                           f"(run directory: {rundir})")
    if not result.verdict.ok:  # measured all the same, and said on stderr (the bench's rows show it too)
        print(f"dmosim run {' '.join(flags)}: {err.strip()}", file=sys.stderr)
    compute, messages = agents_reported(result)
    if keep is None:
        shutil.rmtree(rundir, ignore_errors=True)
    return {"result": result, "compute": compute, "messages": messages, "process_s": process_s}
