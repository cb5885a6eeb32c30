"""A flood from one agent's own credentials against a market day: what it costs the DMO, the recorder and the day.

The same tiny day (N agents, ``--scenarios 1 --subperiods 1`` by default) runs twice, as roles started by hand the way
docs/hosts.md starts them: the run's credentials made for N + 1 agents (``create_auth_dir``, as ``dmosim credentials
--agents N+1`` makes them), ``dmosim dmo --auth-dir`` (the router) with a fleet of N, ``dmosim record``, ``dmosim
agent`` for each of the N. The second run adds the flooder: a process that holds the bundle of agent N + 1 alone (its
password, and its certificate with ``--tls``), logs in as a client as any agent does, and for ``--flood`` seconds
(or until the DMO has exited) sends, all four at once, each from a thread of its own (docs/benchmarks.md, "flood"):

1. ``oversized``: payloads that fail validation on its own meter key, of exactly 1 MiB (the cap: parsed, then
   refused as ``invalid``) and 1 MiB + 1 byte (refused as ``oversize``), in turn;
2. ``resent``: one valid-looking meter report, the same bytes again and again;
3. ``sequenced``: well-formed meter reports, bids and schedules (and registrations once registration is over, when
   they can only be refused) with a new ``seq`` each;
4. ``history``: ``QUERIES_AT_ONCE`` queries ``dmosim/<run>/dmo/clock?history`` at once, and as many
   ``dmosim/<run>/**?history`` (which access control refuses an agent), round after round, counting the replies.

The flooder needs nothing of the DMO but what any agent hears: it asks for the clock to learn the run's token and
market day (and floods with none if no answer comes). It counts what it sent into a file when it stops.

While each run goes, the DMO's and the recorder's resident memory is sampled every ``--sample`` seconds, and the
DMO's journal's size; afterwards ``dmosim info``, ``dmosim settle`` and ``dmosim export`` run on the flooded
recording, and the honest agents' bills of the two runs are compared. Every process is stopped whatever happens.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from dmo.operator.report import DmoReport
from messages import Bid, MeterReport, Registration, Schedule, decode, encode
from messages.codec import MAX_PAYLOAD_BYTES, MessageError
from messages.keys import new_run_id
from messages.schemas import HOURS
from messages.transport import Bus, BusConfig
from messages.transport.access import bundle_settings
from messages.transport.credentials import create_auth_dir

from ..arguments import gap, integer, market_day, nonneg_float, positive_int, today
from ..console import stopping_on_terminate
from ..experiment.spec import Agents, Deadlines, Experiment, Market, ScheduleSettings, to_toml
from ..launch.processes import (COMMAND_STOP_S, ROLE_STOP_S, Command, Roles, dmosim_command, free_port,
                                interrupts_held, memory_mib, proc_stat, role_env, stop_processes, wait_listening)
from ..launch.roles import fleet_of
from ..results.report import read_result
from .day import bench_root

FLOOD_S = 60.0  # how long the flooder floods, unless the DMO is gone first
FLOOD_PATTERNS = ("oversized", "resent", "sequenced", "history")
OVERSIZED_KINDS = 8  # different payloads of each size the flooder sends in turn
QUERIES_AT_ONCE = 100  # history queries the flooder has in flight at once, of each selector
QUERY_TIMEOUT_S = 5.0  # how long a query may go unanswered (access control drops a refused one without a reply)
FLOODER_JOIN_S = 2.0  # how long the stopped flooder waits for its threads before it writes its counts
TOKEN_WAIT_S = 30.0  # how long the flooder asks for the clock before it floods without the run's token
SAMPLE_S = 0.2  # how often the DMO's and the recorder's memory and the journal's size are sampled
DMO_CAP_MIB = 6144.0  # a DMO past this resident size is stopped: the machine is shared (the run then fails)
VERB_TIMEOUT_S = 900.0  # each of info, settle and export on the flooded recording
RECORDER_FINISH_S = 60.0  # how long the recorder has to finish its file once the run is over
AGENTS_LEAVE_S = 60.0  # how long the agents have to leave once the DMO has exited
# The goals of issue 43: what one agent's flood may cost the day and the DMO.
FLOOD_GOAL_WALL_RATIO = 1.5  # the flooded day's wall time over the honest one's
FLOOD_GOAL_DMO_MIB = 300.0  # the DMO's peak resident memory while flooded
FLOOD_GOAL_JOURNAL_MIB = 50.0  # what the flood adds to the DMO's journal
FLOODER = "flooder"  # the flooder's role name (its log, its line of memory); its agent id is the fleet's next
MIB = 1 << 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agents", type=integer(1, 99), default=3, help="honest agents (default: 3)")
    parser.add_argument("--scenarios", type=positive_int, default=1, help="scenarios per agent schedule (default: 1)")
    parser.add_argument("--subperiods", type=positive_int, default=1, help="sub-periods per hour (default: 1)")
    parser.add_argument("--gap", type=gap, default=0.05, help="relative MIP gap of the schedules (default: 0.05)")
    parser.add_argument("--days", type=integer(1, 30), default=1, help="market days (default: 1)")
    parser.add_argument("--seed", type=integer(0, 2**32 - 1), default=0, help="the run's seed (default: 0)")
    parser.add_argument("--market-day", type=market_day, default=None,
                        help="the first market day, YYYY-MM-DD, the same in both runs (default: today)")
    parser.add_argument("--flood", type=nonneg_float, default=FLOOD_S, metavar="S",
                        help=f"seconds the flooder floods, unless the DMO is gone first (default: {FLOOD_S:g})")
    parser.add_argument("--tls", action="store_true", help="every role, the flooder too, over mutual TLS")
    parser.add_argument("--sample", type=nonneg_float, default=SAMPLE_S, metavar="S",
                        help=f"seconds between samples of memory and the journal (default: {SAMPLE_S:g})")
    parser.add_argument("--dmo-cap-mib", type=nonneg_float, default=DMO_CAP_MIB, metavar="MIB",
                        help=f"stop a DMO whose resident memory passes this, MiB (default: {DMO_CAP_MIB:g})")
    parser.add_argument("--out", metavar="DIR", help="keep both runs in DIR/honest and DIR/flooded (default: a "
                                                     "scratch directory, removed unless a run fails)")
    parser.add_argument("--timeout", type=nonneg_float, default=1800.0,
                        help="seconds each run may take before the bench stops it (default: 1800)")


def run(args) -> dict:
    experiment = Experiment(
        name="flood", seed=args.seed, days=args.days, market_day=args.market_day or today(),
        agents=Agents(count=args.agents), market=Market(subperiods=args.subperiods),
        schedule=ScheduleSettings(scenarios=args.scenarios, gap=args.gap),
        # generous deadlines: a slowed day shows in its wall time, not as reports missed
        deadlines=Deadlines(registration=300.0, bid=600.0, schedule=600.0, hour=120.0))
    with bench_root(args.out, "flood") as root, stopping_on_terminate():
        runs = {name: run_day(experiment, root / name, args, flood=args.flood if name == "flooded" else None)
                for name in ("honest", "flooded")}
        verbs = run_verbs(runs["flooded"]["recording"], root / "flooded" / "tables")
    return report(experiment, args, runs, verbs, Path(args.out) if args.out else None)


# --- one run: the roles as docs/hosts.md starts them ---------------------------------------------------------------

def run_day(experiment: Experiment, rundir: Path, args, flood: float | None) -> dict:
    """One run of ``experiment`` in ``rundir`` (logs, journal, result, recording), with the flooder if ``flood`` (its
    seconds): what was measured, the DMO's result (None if it left none) and the flooder's counts."""
    rundir.mkdir(parents=True, exist_ok=True)
    for stale in rundir.iterdir():  # a kept directory of an earlier bench: its files would be read as this run's
        shutil.rmtree(stale) if stale.is_dir() else stale.unlink()
    fleet = [m.id for m in fleet_of(experiment)]
    intruder = next(f"mg{i}" for i in range(len(fleet) + 1, 10_000) if f"mg{i}" not in fleet)
    files = {name: rundir / name for name in ("experiment.toml", "result.json", "dmo.journal", "recording.mcap",
                                               "recorder.ready", "flood.json")}
    files["experiment.toml"].write_text(to_toml(experiment))
    run_id, port = new_run_id(), free_port()
    scheme = "tls" if args.tls else "tcp"
    endpoint = f"{scheme}/127.0.0.1:{port}"
    common = ["--run-id", run_id, "--experiment", str(files["experiment.toml"])]
    watch = Sampler(args.sample)
    measured: dict = {"run_id": run_id, "agents": fleet, "flooder_id": intruder if flood is not None else None}
    # The credentials live in a private directory while the run does, never in the run directory (docs/security.md).
    with tempfile.TemporaryDirectory(prefix=f"dmosim-{run_id}-") as private, Roles() as roles:
        auth = create_auth_dir(Path(private) / "auth", run_id, [*fleet, intruder], tls=args.tls, valid_days=1,
                               dmo_client=False)
        login = ["--auth-dir", str(auth)]
        start = time.monotonic()
        dmo = roles.start("dmo", dmosim_command(
            "dmo", *common, *login, "--listen", endpoint, "--result", str(files["result.json"]),
            "--journal", str(files["dmo.journal"]), "--await-recorder", "60"), log=rundir / "dmo.log", env=role_env())
        wait_listening(port, 60, lambda: dmo.process.poll() is None)
        recorder = roles.start("recorder", dmosim_command(
            "record", "--out", str(files["recording.mcap"]), "--run-id", run_id, "--connect", endpoint, *login,
            "--ready-file", str(files["recorder.ready"]), *recording_flags(experiment, fleet, files)),
            log=rundir / "recorder.log", env=role_env())
        _wait_for_file(files["recorder.ready"], 90, {"dmo": dmo, "recorder": recorder})
        for agent in fleet:
            roles.start(agent, dmosim_command("agent", *common, "--id", agent, "--connect", endpoint, *login),
                        log=rundir / f"{agent}.log", env=role_env())
        watched = {"dmo": dmo.process.pid, "recorder": recorder.process.pid}
        if flood is not None:
            flooder = roles.start(FLOODER, [sys.executable, "-m", "dmosim.bench.flood", "--flooder", "--run-id", run_id,
                                            "--id", intruder, "--connect", endpoint, "--auth-dir", str(auth),
                                            "--seconds", repr(flood), "--counts", str(files["flood.json"])],
                                  log=rundir / f"{FLOODER}.log", env=role_env())
            watched[FLOODER] = flooder.process.pid
        with watch.running(watched, cap=("dmo", args.dmo_cap_mib, roles)):
            exits = _await_dmo(roles, start + args.timeout, watch, rundir)
            measured["wall_s"] = round(time.monotonic() - start, 2)
            if flood is not None:  # the flood ends with the day: the DMO it floods is gone
                stop_processes([roles.roles[FLOODER].process], ROLE_STOP_S)
            _await_agents(roles, fleet, exits)
            measured["recorder_exit"] = _finish_recording(roles)
        if watch.capped:
            raise RuntimeError(f"the DMO passed {args.dmo_cap_mib:g} MiB of resident memory and was stopped "
                               f"(run directory: {rundir})")
    result = read_result(files["result.json"], DmoReport) if files["result.json"].is_file() else None
    if result is None:
        raise RuntimeError(f"the DMO left no result (exit {exits.get('dmo')}; its log: {rundir / 'dmo.log'})")
    counts = json.loads(files["flood.json"].read_text()) if files["flood.json"].is_file() else None
    if flood is not None and counts is None:
        raise RuntimeError(f"the flooder left no counts (its log: {rundir / f'{FLOODER}.log'})")
    return {**measured, "result": result, "exits": exits, "flood": counts, "samples": watch.summary(),
            "journal_bytes": _size(files["dmo.journal"]), "recording": files["recording.mcap"],
            "recording_bytes": _size(files["recording.mcap"]), "dmo_log_bytes": _size(rundir / "dmo.log")}


def recording_flags(experiment: Experiment, fleet: list[str], files: dict[str, Path]) -> list[str]:
    """The recorder's metadata and attachment, as ``dmosim run`` gives its own: the resolved experiment."""
    meta = {"config": json.dumps(experiment.model_dump(), sort_keys=True), "seed": str(experiment.seed),
            "market_day": experiment.market_day, "days": str(experiment.days), "agents": ",".join(fleet),
            "command": "dmosim bench flood"}
    return [f for k, v in meta.items() for f in ("--meta", f"{k}={v}")] + ["--attach", str(files["experiment.toml"])]


def _wait_for_file(path: Path, timeout_s: float, roles: dict) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        for name, role in roles.items():
            if role.process.poll() is not None:
                raise RuntimeError(f"{name} exited before {path.name} appeared; its log: {role.log}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"no {path} within {timeout_s:g} s")
        time.sleep(0.05)  # paces the looks at a file another process writes


def _await_dmo(roles: Roles, deadline: float, watch: Sampler, rundir: Path) -> dict[str, int]:
    """Block on exits until the DMO's; name -> exit code of every role that exited meanwhile."""
    exits: dict[str, int] = {}
    while "dmo" not in exits:
        try:
            name, code = roles.exits.get(timeout=min(1.0, max(0.0, deadline - time.monotonic())))
        except queue.Empty:
            if watch.capped:
                continue  # the sampler stopped the DMO: its exit comes
            if time.monotonic() >= deadline:
                raise RuntimeError(f"the run took longer than the bench's timeout and was stopped (run directory: "
                                   f"{rundir})") from None
            continue
        exits[name] = code
    return exits


def _await_agents(roles: Roles, fleet: list[str], exits: dict[str, int]) -> None:
    """The agents leave once they have their last statements; those still there after ``AGENTS_LEAVE_S`` are
    stopped (their exit code then that of the signal, negative)."""
    deadline = time.monotonic() + AGENTS_LEAVE_S
    while any(a not in exits for a in fleet) and time.monotonic() < deadline:
        with contextlib.suppress(queue.Empty):
            name, code = roles.exits.get(timeout=0.5)
            exits[name] = code
    stop_processes([roles.roles[a].process for a in fleet if a not in exits], ROLE_STOP_S)
    for agent in fleet:
        exits.setdefault(agent, roles.roles[agent].process.returncode)


def _finish_recording(roles: Roles) -> int | None:
    """SIGTERM the recorder: it writes its last chunk, the summary and the footer. Its exit code (None: it did not
    finish within ``RECORDER_FINISH_S`` and was killed)."""
    process = roles.roles["recorder"].process
    if process.poll() is None:
        time.sleep(0.2)  # what the DMO sent last is still on its way
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=RECORDER_FINISH_S)
    except subprocess.TimeoutExpired:
        stop_processes([process], ROLE_STOP_S)
        return None


def _size(path: Path) -> int | None:
    return path.stat().st_size if path.is_file() else None


class Sampler:
    """Samples the resident memory (``memory_mib``) and CPU time of some processes on a thread of its own, every
    ``interval`` seconds; and stops one process whose resident memory passes a cap."""

    def __init__(self, interval: float):
        self.interval = max(interval, 0.01)
        self.peak: dict[str, float] = {}  # name -> largest sampled RSS, MiB
        self.hwm: dict[str, float] = {}  # name -> the kernel's own peak (VmHWM) at its last sample, MiB
        self.cpu: dict[str, float] = {}  # name -> user + system CPU seconds at its last sample
        self.samples = 0
        self.capped = False

    @contextlib.contextmanager
    def running(self, pids: dict[str, int], cap: tuple[str, float, Roles] | None = None):
        done = threading.Event()
        thread = threading.Thread(target=self._loop, args=(pids, cap, done), name="sampler", daemon=True)
        thread.start()
        try:
            yield self
        finally:
            done.set()
            thread.join()

    def _loop(self, pids: dict[str, int], cap, done: threading.Event) -> None:
        tick = os.sysconf("SC_CLK_TCK")
        while True:
            for name, pid in pids.items():
                memory = memory_mib(pid)
                if memory is None:
                    continue
                self.peak[name] = max(self.peak.get(name, 0.0), memory["rss_mib"])
                self.hwm[name] = memory["peak_mib"]
                fields = proc_stat(pid)
                if len(fields) > 12:
                    self.cpu[name] = (int(fields[11]) + int(fields[12])) / tick
                if cap and name == cap[0] and memory["rss_mib"] > cap[1] and not self.capped:
                    self.capped = True
                    stop_processes([cap[2].roles[name].process], ROLE_STOP_S)
            self.samples += 1
            if done.wait(self.interval):
                return

    def summary(self) -> dict:
        return {"peak_rss_mib": dict(self.peak), "hwm_mib": dict(self.hwm), "cpu_s": dict(self.cpu),
                "samples": self.samples}


# --- afterwards: the verbs on the flooded recording -----------------------------------------------------------------

def run_verbs(recording: Path, tables: Path) -> list[dict]:
    """``dmosim info``, ``settle`` and ``export`` on the recording, one after the other: exit code, wall time, peak
    resident memory, and what settle said (whether re-settling reproduced the recorded statements)."""
    rows = []
    for verb, more in (("info", ["--json"]), ("settle", ["--json"]), ("export", ["--out", str(tables)])):
        argv = dmosim_command(verb, str(recording), *more)
        watch = Sampler(SAMPLE_S)
        start = time.perf_counter()
        command = None
        try:
            with interrupts_held():
                command = Command(argv)
            with watch.running({verb: command.pid}):
                code = command.wait(VERB_TIMEOUT_S)
        except BaseException as exc:
            if command is not None:
                stop_processes([command.process], COMMAND_STOP_S)
            if isinstance(exc, subprocess.TimeoutExpired):
                code = None
            else:
                raise
        row = {"verb": verb, "exit": code, "wall_s": round(time.perf_counter() - start, 2),
               "peak_rss_mib": watch.peak.get(verb)}
        out, err = command.output()
        if verb == "settle":
            row["identical"] = _said(out).get("identical")
        elif verb == "info":
            row["messages"] = _said(out).get("messages")
        if code != 0:
            row["error"] = (err.strip().splitlines() or ["(nothing on stderr)"])[-1][:300]
        rows.append(row)
    return rows


def _said(out: str) -> dict:
    try:
        said = json.loads(out)
    except ValueError:
        return {}
    return said if isinstance(said, dict) else {}


# --- the report ------------------------------------------------------------------------------------------------------

def report(experiment: Experiment, args, runs: dict[str, dict], verbs: list[dict], kept: Path | None) -> dict:
    honest, flooded = runs["honest"], runs["flooded"]
    rows = [_row(name, r) for name, r in runs.items()]
    counts = flooded["flood"]
    journal_growth = (flooded["journal_bytes"] or 0) - (honest["journal_bytes"] or 0)
    wall_ratio = flooded["wall_s"] / honest["wall_s"]
    # the larger of the sampled peak and the kernel's high-water mark, which catches a peak between samples
    dmo_peak = max((m for m in (rows[1]["dmo_peak_mib"], rows[1]["dmo_hwm_mib"]) if m is not None), default=None)
    bills = compare_bills(honest["result"], flooded["result"], honest["agents"])
    settled = next((v.get("identical") for v in verbs if v["verb"] == "settle"), None)
    return {
        "setup": {"agents": f"{args.agents} honest (mg1..mg{args.agents}) + 1 flooder ({flooded['flooder_id']}, its "
                            "own credentials only, not in the DMO's fleet)",
                  "day": f"{experiment.days} day(s), {args.scenarios} scenario(s), {args.subperiods} sub-period(s), "
                         f"gap {args.gap}, market day {experiment.market_day}, seed {experiment.seed}",
                  "flood": f"up to {args.flood:g} s, the four patterns at once, each on a thread of its own; stopped "
                           "when the DMO exits",
                  "transport": "TLS" if args.tls else "TCP on loopback, user and password",
                  "machine": f"{os.cpu_count() or 1} cores shared with other work: one run each, noisy",
                  **({"kept": str(kept)} if kept else {})},
        "runs": rows,
        "flood": {"flooded_s": round(counts["flooded_s"], 1), "token_learned": counts["token_learned"],
                  "flooder_cpu_s": flooded["samples"]["cpu_s"].get(FLOODER),
                  "link_closed": counts["link_closed"],
                  "reached_dmo": reached(honest["result"], flooded["result"]),
                  "patterns": flood_rows(counts), "history": history_rows(counts)},
        "dmo_refused": {"by_code": flooded["result"].rejected_by_code,
                        "transport": flooded["result"].transport},
        "verbs": verbs,
        "bills": bills,
        "ratios": {"wall flooded / honest": round(wall_ratio, 3),
                   "dmo peak flooded / honest": _ratio(dmo_peak, max(rows[0]["dmo_peak_mib"] or 0,
                                                                      rows[0]["dmo_hwm_mib"] or 0)),
                   "journal flooded / honest": _ratio(flooded["journal_bytes"], honest["journal_bytes"]),
                   "recording flooded / honest": _ratio(flooded["recording_bytes"], honest["recording_bytes"])},
        "goals": [
            _goal("wall flooded / honest", round(wall_ratio, 3), f"< {FLOOD_GOAL_WALL_RATIO:g}",
                  wall_ratio < FLOOD_GOAL_WALL_RATIO),
            _goal("DMO peak RSS while flooded, MiB", dmo_peak, f"< {FLOOD_GOAL_DMO_MIB:g}",
                  dmo_peak is not None and dmo_peak < FLOOD_GOAL_DMO_MIB),
            _goal("journal growth, MiB", round(journal_growth / MIB, 2), f"< {FLOOD_GOAL_JOURNAL_MIB:g}",
                  journal_growth / MIB < FLOOD_GOAL_JOURNAL_MIB),
            _goal("info, settle, export exit 0", ", ".join(str(v["exit"]) for v in verbs), "0, 0, 0",
                  all(v["exit"] == 0 for v in verbs)),
            _goal("re-settled = recorded statements", settled, "True", settled is True),
            _goal("honest bills the same in both runs", bills["same"], "True", bills["same"]),
        ],
    }


def _row(name: str, run: dict) -> dict:
    """One run's figures: wall time, the DMO's phases, memory and CPU, what it wrote and refused, the recording."""
    result, samples = run["result"], run["samples"]
    days = result.days
    return {"run": name, "wall_s": run["wall_s"],
            "registration_s": round(sum(d.phase_s.get("registration", 0.0) for d in days), 2),
            "day_s": round(sum(v for d in days for k, v in d.phase_s.items() if k != "registration"), 2),
            "dmo_peak_mib": samples["peak_rss_mib"].get("dmo"), "dmo_hwm_mib": samples["hwm_mib"].get("dmo"),
            "dmo_cpu_s": samples["cpu_s"].get("dmo"),
            "recorder_peak_mib": samples["peak_rss_mib"].get("recorder"),
            "journal_mib": _mib(run["journal_bytes"]),
            "dmo_log_mib": _mib(run["dmo_log_bytes"]), "recording_mib": _mib(run["recording_bytes"]),
            "rejected": result.rejected_messages, "incidents": len(result.incidents),
            "agents_exit": ",".join(str(run["exits"].get(a)) for a in run["agents"]),
            "recorder_exit": run["recorder_exit"]}


def flood_rows(counts: dict | None) -> list[dict]:
    """What the flooder put, per pattern: messages (history: queries), MiB (history: of replies), the rate over the
    time it flooded, and the puts that failed. A put is not a message delivered: what is put while Zenoh closes a
    congested link goes nowhere (``Flood.watch_link``); ``reached`` says what the DMO took in."""
    seconds = counts["flooded_s"] or math.nan
    return [{"pattern": name, "puts": c["sent"], "mib": round(c["bytes"] / MIB, 1),
             "per_s": round(c["sent"] / seconds, 1), "errors": c["errors"]} for name, c in counts["patterns"].items()]


def history_rows(counts: dict | None) -> list[dict]:
    """The history queries, per selector (the run's prefix cut): sent, answered (a reply), refused (error replies
    only: the DMO busy), unanswered within ``QUERY_TIMEOUT_S`` (access control drops what it refuses), the replies,
    error replies and MiB of replies."""
    return [{"selector": selector.split("/", 2)[-1], **{k: v for k, v in c.items() if k != "reply_bytes"},
             "reply_mib": round(c["reply_bytes"] / MIB, 2)}
            for selector, c in counts["patterns"]["history"]["selectors"].items()]


def reached(honest: DmoReport, flooded: DmoReport) -> int:
    """How many of the flooder's messages reached the DMO: every one is refused (it never registers) or dropped
    unread by the DMO's gate (``transport.dropped``, where there is one), less what the honest run refused."""
    return (flooded.rejected_messages + flooded.transport.get("dropped", 0)
            - honest.rejected_messages - honest.transport.get("dropped", 0))


def compare_bills(honest: DmoReport, flooded: DmoReport, agents: list[str]) -> dict:
    """The honest agents' settlements (every figure of the DMO's result) in the two runs, to the cent; a differing
    figure is listed as agent.figure: honest -> flooded."""
    differences = []
    for agent in agents:
        a, b = honest.settlement.get(agent), flooded.settlement.get(agent)
        if a is None or b is None:
            differences.append(f"{agent}: {'settled' if a else 'not settled'} honest, "
                               f"{'settled' if b else 'not settled'} flooded")
            continue
        differences += [f"{agent}.{k}: {getattr(a, k)} -> {getattr(b, k)}" for k in type(a).model_fields
                        if not math.isclose(getattr(a, k), getattr(b, k), abs_tol=0.005)]
    totals = {a: [s.total if (s := honest.settlement.get(a)) else None,
                  s.total if (s := flooded.settlement.get(a)) else None] for a in agents}
    return {"same": not differences, "totals honest, flooded": totals, **({"differences": differences[:20]}
                                                                           if differences else {})}


def _goal(what: str, value, target: str, met: bool) -> dict:
    return {"goal": what, "value": value, "target": target, "met": bool(met)}


def _ratio(a, b) -> float | None:
    return round(a / b, 2) if a is not None and b else None


def _mib(size: int | None) -> float | None:
    return None if size is None else round(size / MIB, 2)


# --- the flooder ---------------------------------------------------------------------------------------------------

class Flood:
    """The flooder's four patterns on one bus, each on a thread of its own until ``stop`` is set, and what each sent."""

    def __init__(self, bus: Bus, stop: threading.Event):
        self.bus, self.stop = bus, stop
        self.phase = "registration"  # where the DMO's clock stands, as last heard
        self.market_day = today()
        self.token_learned = False
        self.counts = {name: {"sent": 0, "bytes": 0, "errors": 0} for name in FLOOD_PATTERNS}
        self.counts["history"]["selectors"] = {}
        self.lock = threading.Lock()  # the counts of the history's replies, which Zenoh's threads update
        self.link_closed = 0  # times Zenoh closed the flooder's own link to the DMO (the client then connects again)
        self._link_events = None

    def watch_link(self) -> None:
        """Count the times Zenoh closes this session's link to the DMO: a put that waits longer than Zenoh's
        ``wait_before_close`` (5 s) for room on a congested link has it closed, and what is put while it closes
        (about 5 s more) goes nowhere, at thousands of puts a second: counted as put, it never arrived."""
        self._link_events = self.bus.session.info.declare_transport_events_listener(self._on_transport)

    def _on_transport(self, event) -> None:
        if event.kind == zenoh.SampleKind.DELETE:
            with self.lock:
                self.link_closed += 1

    def learn(self, timeout_s: float) -> None:
        """Ask for the DMO's clock, as an agent does, until it answers: the run's token and market day."""
        self.bus.subscribe(self.bus.keys.clock(), self._on_clock)
        deadline = time.monotonic() + timeout_s
        while not self.stop.is_set() and time.monotonic() < deadline:
            for _, payload, _ in self.bus.fetch(self.bus.keys.clock(), timeout_s=2.0):
                with contextlib.suppress(MessageError):
                    self._on_clock(None, decode(payload, expected_kind="clock"), 0)
            if self.token_learned:
                return
            self.stop.wait(0.5)

    def _on_clock(self, key, msg, received_at) -> None:
        self.bus.run_token = msg.run
        self.phase, self.market_day, self.token_learned = msg.phase, msg.market_day, True

    def threads(self) -> list[threading.Thread]:
        return [threading.Thread(target=self._guarded, args=(name,), name=name, daemon=True) for name in FLOOD_PATTERNS]

    def _guarded(self, name: str) -> None:
        while not self.stop.is_set():
            try:
                getattr(self, name)(self.counts[name])
            except Exception:  # the DMO (the router) is gone, or a put failed: count it and go on
                self.counts[name]["errors"] += 1
                self.stop.wait(0.1)

    def _put(self, counts: dict, key: str, payload: bytes) -> None:
        self.bus.republish(key, payload)
        self._count(counts, payload)

    @staticmethod
    def _count(counts: dict, payload: bytes) -> None:
        counts["sent"] += 1
        counts["bytes"] += len(payload)

    def oversized(self, counts: dict) -> None:
        """Payloads on its own meter key that fail validation, exactly at the 1 MiB cap (parsed, then refused) and one
        byte over it (refused unread), in turn; ``OVERSIZED_KINDS`` different ones of each, of random readings, so
        that neither a recording's compression nor a cache of what was seen makes them cheap."""
        key = self.bus.keys.meter(self.bus.name)
        rng = random.Random(0)
        payloads = []
        for _ in range(OVERSIZED_KINDS):
            at_cap = self._padded(MAX_PAYLOAD_BYTES, rng)
            payloads += [at_cap, at_cap + b" "]
        while not self.stop.is_set():
            for payload in payloads:
                self._put(counts, key, payload)

    def _padded(self, size: int, rng: random.Random) -> bytes:
        """A meter report of this agent with far too many readings (invalid), blank-padded to ``size`` bytes."""
        before, after = encode(self._meter(1)).decode().split('"p_m_mw":[0.5]')
        room = size - len(before) - len(after) - len('"p_m_mw":[0.12345]')
        readings = ",".join(f"{rng.random():.5f}" for _ in range(room // 8))  # "0.12345," is 8 bytes
        body = before + '"p_m_mw":[' + readings + ",0.12345]" + after
        return (body[:-1] + " " * (size - len(body)) + "}").encode()

    def resent(self, counts: dict) -> None:
        """One well-formed meter report, stamped once, the same bytes again and again."""
        payload, key = encode(self.bus.publish(self._meter(1))), self.bus.keys.meter(self.bus.name)
        self._count(counts, payload)
        while not self.stop.is_set():
            self._put(counts, key, payload)

    def sequenced(self, counts: dict) -> None:
        """Well-formed messages with a new seq each: meter reports of every hour, bids, schedules, and registrations
        once registration is over (during it one would register the flooder: it may only be refused)."""
        n = 0
        while not self.stop.is_set():
            n += 1
            kinds = [self._meter(n % HOURS + 1), self._bid(), self._schedule()]
            if self.phase != "registration":
                kinds.append(Registration(sender=self.bus.name, market_day=self.market_day, case="paper",
                                          max_import_mw=1.0, max_export_mw=1.0, strategy=None, bus=None))
            for msg in kinds:
                self.bus.publish(msg, before_put=lambda key, payload, stamped: self._count(counts, payload))

    def history(self, counts: dict) -> None:
        """``QUERIES_AT_ONCE`` queries of each selector in flight at once; the next round once all are done. Replies
        are counted as they come, each query as answered (a reply), refused (error replies only) or unanswered
        (nothing within ``QUERY_TIMEOUT_S``: access control drops a query it refuses) when Zenoh finishes it."""
        prefix = self.bus.keys.prefix
        tallies = [counts["selectors"].setdefault(s, {"queries": 0, "answered": 0, "refused": 0, "unanswered": 0,
                                                      "replies": 0, "error_replies": 0, "reply_bytes": 0})
                   for s in (f"{prefix}/dmo/clock?history", f"{prefix}/**?history")]
        finished = []
        for selector, tally in zip(counts["selectors"], tallies):
            for _ in range(QUERIES_AT_ONCE):
                got, done = {"ok": 0, "err": 0}, threading.Event()

                def on_reply(reply, tally=tally, got=got):
                    with self.lock:
                        if reply.ok is None:
                            got["err"] += 1
                            tally["error_replies"] += 1
                            return
                        size = len(reply.ok.payload.to_bytes())
                        got["ok"] += 1
                        tally["replies"] += 1
                        tally["reply_bytes"] += size
                        counts["bytes"] += size

                def on_done(tally=tally, got=got, done=done):
                    with self.lock:
                        what = "answered" if got["ok"] else "refused" if got["err"] else "unanswered"
                        tally[what] += 1
                    done.set()

                with self.lock:
                    tally["queries"] += 1
                    counts["sent"] += 1
                self.bus.session.get(selector, zenoh.handlers.Callback(on_reply, on_done), timeout=QUERY_TIMEOUT_S,
                                     consolidation=zenoh.ConsolidationMode.NONE)
                finished.append(done)
        for done in finished:
            while not done.wait(0.2):
                if self.stop.is_set():
                    return

    def snapshot(self) -> dict:
        """What was sent so far, and the link's closures, copied whole (Zenoh's threads count replies and closures)."""
        with self.lock:
            return json.loads(json.dumps({"patterns": self.counts, "link_closed": self.link_closed}))

    def _meter(self, hour: int) -> MeterReport:
        return MeterReport(sender=self.bus.name, market_day=self.market_day, hour=hour, subperiods=1, p_m_mw=(0.5,),
                           deviation_mw=(0.0,))

    def _bid(self) -> Bid:
        return Bid(sender=self.bus.name, market_day=self.market_day, hours=((),) * HOURS)

    def _schedule(self) -> Schedule:
        return Schedule(sender=self.bus.name, market_day=self.market_day, status="optimal", commitment={},
                        expected_cost=0.0, p_m_expected_mw=(0.0,) * HOURS, scenarios=1, mip_gap=None)


def flooder_main(run_id: str, agent: str, endpoint: str, auth: str, seconds: float, counts_file: str) -> int:
    """Log in with ``agent``'s own bundle, learn the run's token from the clock, flood for ``seconds`` (or until
    SIGTERM), then write what was sent to ``counts_file`` (whole, or not at all) before leaving."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    config = BusConfig(mode="client", connect=(endpoint,), connect_timeout_s=60.0,
                       overrides=bundle_settings(auth, agent))
    with Bus(run_id, agent, config) as bus:
        flood = Flood(bus, stop)
        flood.watch_link()
        flood.learn(TOKEN_WAIT_S)
        began = time.monotonic()
        threads = flood.threads()
        for thread in threads:
            thread.start()
        stop.wait(seconds)
        stop.set()
        flooded_s = time.monotonic() - began
        joined = time.monotonic() + FLOODER_JOIN_S  # well within the grace a stopped role gets (ROLE_STOP_S)
        for thread in threads:  # a put blocked on a gone router may not return: its counts are read as they stand
            thread.join(max(0.0, joined - time.monotonic()))
        out = Path(counts_file)
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps({"agent": agent, "token_learned": flood.token_learned, "flooded_s": flooded_s,
                                   **flood.snapshot()}, indent=2))
        tmp.replace(out)
    return 0


if __name__ == "__main__":
    cli = argparse.ArgumentParser(prog="python -m dmosim.bench.flood", description="the flooder of the flood bench")
    cli.add_argument("--flooder", action="store_true", required=True)
    cli.add_argument("--run-id", required=True)
    cli.add_argument("--id", required=True, help="the agent whose bundle the flooder holds")
    cli.add_argument("--connect", required=True)
    cli.add_argument("--auth-dir", required=True)
    cli.add_argument("--seconds", type=float, required=True)
    cli.add_argument("--counts", required=True, help="where to write what was sent")
    a = cli.parse_args()
    sys.exit(flooder_main(a.run_id, a.id, a.connect, a.auth_dir, a.seconds, a.counts))
