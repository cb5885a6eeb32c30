"""A run on this machine: the DMO, one process per agent and the recorder, started from an experiment over Zenoh on
loopback with credentials made for the run (in a private temporary directory, never in the run directory), watched
(process faults fire on the DMO's clock) and always stopped.
With ``agents.hosting = "fork"`` each agent's process is forked from one host that has imported the agent's code
(host.py), instead of starting a Python of its own; the agents run the same command either way. With a ``cluster``
the agents run on its workers instead (cluster.py), the DMO listening for them on every interface of this machine.

``run_locally`` returns the DMO's result (``RunResult.report``: what the agents realised is in it, from their
``agent_day`` messages, never from their logs) with where the recording went and the run's verdict
(dmosim/results/verdict.py); it writes what the run makes into its run directory (experiment/rundir.py). The
recorder is an observer: if it fails, the days go on and settle, and the tables come from the DMO's journal.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterable

from dmo.market.choice import Trust, UntrustedRule
from dmo.operator.config import LOGICAL, WALL
from dmo.operator.report import DmoReport
from dmo.replay.resettle import resettled_differences
from dmo.replay.reproduce import differences, statements_of
from messages import HOURS, Clock, Schedule
from messages.keys import new_run_id
from messages.recording import Recording, RecordingError, read_recording
from messages.transport import Bus, BusConfig
from messages.transport.access import bundle_settings
from messages.transport.credentials import DEFAULT_HOSTS, create_auth_dir, read_bundle
from scenarios.case import case_path
from scenarios.fleet import FleetMember

from ..experiment.rundir import RunDir
from ..experiment.spec import IN_PROCESS, MAX_SECONDS, Experiment, load_experiment, to_toml
from ..results.journaled import journal_recording
from ..results.report import (Placement, Recorded, Reproduced, Resettled, Routers, RunReport, read_result,
                              result_text)
from ..results.verdict import problems, verdict
from .cluster import Cluster, RemoteAgents, endpoint
from .faults import Fault, parse_fault
from .mesh import router_names, spread, start_routers
from .processes import Roles, dmosim_command, free_port, memory_mib, wait_listening
from .roles import fleet_of, fleet_written, hosting_of, resolved
from .viewing import Viewing

OBSERVER = "run"  # the name this process watches the run's clock under
DMO_KILL_AFTER_S = 0.5  # a DMO restart fires mid-hour: the agents' answers are on their way when it dies
RECORDER_STOP_S = 60.0  # how long the recorder may take to finish its file once the run is over
AWAIT_RECORDER = "--await-recorder"  # the DMO's first message waits for the recorder (seconds: STARTING_S)
# How long a role may take to start (the DMO to listen, the recorder to join, the DMO's first message), every role
# watched meanwhile: on the wall clock, a minute; on the logical clock, as long as the roles are alive (a day), for on a
# loaded machine importing the solver stack alone has taken over a minute, and a slow start must not fail a run.
STARTING_S = {WALL: 60.0, LOGICAL: MAX_SECONDS}
# What the host of forked agents imports before it forks them: what `dmosim agent` imports to run a day
# (docs/benchmarks.md, "Hosting agents"), by name: the launcher itself does not load the solver stack.
AGENT_MODULES = ("dmosim.cli.main", "dmosim.cli.agent", "microgrid_agent.agent.process",
                 "microgrid_agent.agent.bidding", "microgrid_agent.agent.slots")
# The lease each agent announces: how long the DMO waits, after an agent's last sign of life, to call a silent one
# vanished. A killed agent's link closes at once, whatever the lease; a live one that is starved of a core for a
# moment must not be called gone: with 1 s, 200 agents bidding at once on 2 cores all vanished within 10 s.
AGENT_LEASE_S = 10.0
IN_PROCESS_LOG = "market.log"  # with hosting = "in-process", the log of the DMO and every agent
HOST = "_host"  # the host of forked agents: its log, its line of memory_mib (no agent id starts with "_")


def groups(agents: list[tuple], per_process: int, alone: set[str]) -> list[list[tuple]]:
    """The agents (name, ...) in the run's order, ``per_process`` to a process, except those named in ``alone``,
    each in a process of its own."""
    out, group = [], []
    for agent in agents:
        if agent[0] in alone:
            out.append([agent])
            continue
        group.append(agent)
        if len(group) == per_process:
            out.append(group)
            group = []
    return out + ([group] if group else [])


def roles_memory(roles: Roles) -> dict[str, dict]:
    """Each role's ``memory_mib`` now, and the agents' host's as ``HOST``. Roles sharing a process (``per_process``)
    each take their share of its PSS, so that the roles' PSS add up to what the run holds; its RSS and peak are the
    process's."""
    pids = {**{name: (role.process.pid, role.shared_by) for name, role in roles.roles.items()},
            **{HOST: (host.process.pid, 1) for host in roles.hosts}}
    sampled = {pid: memory_mib(pid) for pid, _ in set(pids.values())}  # once a process, however many roles it runs
    return {name: {**m, "pss_mib": m["pss_mib"] if m["pss_mib"] is None else round(m["pss_mib"] / shared_by, 1)}
            for name, (pid, shared_by) in pids.items() if (m := sampled[pid]) is not None}


class RoleFailed(RuntimeError):
    """A role of the run failed; ``names`` are the roles, and the message says where their logs are."""

    def __init__(self, names: list[str], roles: Roles, logs: Path):
        self.names = names
        where = {n: roles.roles[n].log if n in roles.roles else logs / f"{n}.log" for n in names}  # remote: its file
        ended = {n: roles.roles[n].process.poll() if n in roles.roles else None for n in names}  # None: still running
        super().__init__("; ".join(f"{n} failed ({'' if ended[n] is None else _exit_status(ended[n], where[n]) + '; '}"
                                   f"its log: {where[n]})" for n in names))


def run_experiment(experiment: Experiment | str | Path, out: str | Path | None = None, *, overwrite: bool = False,
                   record: bool = True, say: Callable[[str], None] = lambda text: None) -> RunReport:
    """A whole experiment (an ``Experiment`` or its file) run on this machine, as ``dmosim run EXPERIMENT`` runs it,
    into the run directory ``out`` (default ``runs/<run_id>``); its result (docs/experiments.md, "The result").
    Bad input raises ``ExperimentError`` or ``RunDirError``; a role that fails, ``RoleFailed``."""
    e = resolved(load_experiment(experiment) if isinstance(experiment, (str, Path)) else experiment)
    run_id = new_run_id()
    rundir = RunDir.make(out, run_id, overwrite)
    e = fleet_written(e, rundir.fleet)
    return run_locally(e, run_id, rundir, record=rundir.recording if record else None, say=say)


def run_locally(experiment: Experiment, run_id: str, rundir: RunDir, *, record: Path | None, tls: bool = False,
                repeat_of: str | Path | None = None, say: Callable[[str], None] = lambda text: None,
                tick: Callable[[int, int, str], None] | None = None, cluster: Cluster | None = None,
                view: Viewing | None = None) -> RunReport:
    """Run ``experiment`` (resolved) as processes; ``record`` is where the recording goes (None: no recorder);
    ``view``, the run's page (viewing.py), started before the DMO's first message (not with hosting in-process);
    with ``cluster``, the agents run on its workers (no process fault may name one: they are not signalled from
    here), which must see the run directory;
    ``repeat_of``, the recording the experiment came from (``--from``), whose statements the run's are compared
    with before its result is written. ``tick(hours done, hours in all, where the clock is[, (day, phase, hour)])``
    follows the DMO's
    clock (``dmosim.console.Progress.update``); without it, ``say`` gets a line per clock message."""
    e = experiment
    fleet = fleet_of(e)
    began = time.monotonic()
    hosting, per_process = hosting_of(e.agents, len(fleet), cluster is not None)  # the run directory's experiment
    e = e.model_copy(update={"agents": e.agents.model_copy(update={"hosting": hosting, "per_process": per_process})})
    rundir.experiment.write_text(to_toml(e))
    if hosting == IN_PROCESS:
        from .inprocess import run_in_process  # noqa: PLC0415  (the solver stack: the launcher of processes needs none)

        say(f"run {run_id}: DMO and {len(fleet)} agents in this process, {e.days} day(s) from {e.market_day}; "
            f"writing to {rundir.root}" + ("" if record else "; not recording"))
        tick = tick or (lambda done, total, text, mark=None: say(text))
        result = run_in_process(e, fleet, run_id, record, recording_inputs(e, fleet, rundir),
                                rundir.logs / IN_PROCESS_LOG, lambda clock: tick(*progress_of(clock)))
        launched = {"experiment": e.name, "faults": [], "restarts": {}, "wall_s": round(time.monotonic() - began, 3),
                    "run_dir": str(rundir.root.resolve()), "logs": str(rundir.logs.resolve()),
                    "recording": str(record.resolve()) if record else None}
        return concluded(result, launched, e, fleet, run_id, rundir, record, repeat_of=repeat_of, say=say)
    return _as_processes(e, fleet, run_id, rundir, record, tls, repeat_of, say, tick, cluster, began, view)


def _as_processes(e: Experiment, fleet: list[FleetMember], run_id: str, rundir: RunDir, record: Path | None,
                  tls: bool, repeat_of: str | Path | None, say: Callable[[str], None],
                  tick: Callable[[int, int, str], None] | None, cluster: Cluster | None, began: float,
                  view: Viewing | None = None) -> RunReport:
    """The run as processes over Zenoh (``run_locally``)."""
    parsed = [parse_fault(f) for f in e.faults]
    faults = [f for f in parsed if isinstance(f, Fault)]  # the roles read the message faults from the experiment
    starting_s = STARTING_S[e.deadlines.clock]
    hosting = e.agents.hosting
    per_process = e.agents.per_process
    names = router_names(e.agents.routers)  # none: the DMO is the router
    tls = tls or len(names) > 1  # routers of a mesh relay for one another over mutual TLS only
    port, scheme = free_port(), "tls" if tls else "tcp"
    local = endpoint(scheme, "127.0.0.1", port)  # where the roles of this machine connect
    # With a cluster the DMO listens on every interface, and the agents connect where the workers reach this machine.
    listen, reach = ((local, local) if cluster is None else
                     (endpoint(scheme, "::" if ":" in cluster.host else "0.0.0.0", port),
                      endpoint(scheme, cluster.host, port)))
    logs = rundir.logs
    # absolute paths: an agent on a cluster's worker starts in another directory
    common = ["--run-id", run_id, "--experiment", str(rundir.experiment.resolve())]
    say(f"run {run_id}: DMO and {len(fleet)} agents on {reach}"
        + (f", the agents on the cluster at {cluster.address}" if cluster else "")
        + f", {e.days} day(s) from {e.market_day}; writing to {rundir.root}" + ("" if record else "; not recording"))
    # The run's credentials live in a private directory of this machine while it runs, never in the run directory
    # (which a cluster's workers share); an agent on a worker gets its own bundle with its task (cluster.py). The
    # directory goes once every role has stopped (the context managers end in reverse order).
    with tempfile.TemporaryDirectory(prefix=f"dmosim-{run_id}-") as private, Roles() as roles, \
            _remote(cluster, run_id, roles) as remote:
        readers = ("recorder", OBSERVER, *([view.name] if view else []))
        auth = create_auth_dir(Path(private) / "auth", run_id, [m.id for m in fleet], readers=readers,
                               tls=tls, valid_days=2, dmo_client=bool(names), routers=tuple(names[1:]),
                               hosts=tuple(dict.fromkeys([*DEFAULT_HOSTS, *([cluster.host] if cluster else [])])))
        login = ["--auth-dir", str(auth)]
        routers = start_routers(roles, names, scheme, run_id, auth, logs, starting_s) if names else []
        if routers:
            local = reach = routers[0]
            say(f"{len(routers)} router(s): " + ", ".join(f"{n} on {at}" for n, at in zip(names, routers)))
        roles.start("dmo", dmosim_command(
            "dmo", *common, *login, *(("--mode", "client", "--connect", local) if routers else ("--listen", listen)),
            "--result", str(rundir.result), "--journal", str(logs / "dmo.journal"),
            *((AWAIT_RECORDER, repr(starting_s)) if record else ())), log=logs / "dmo.log")
        fork = hosting == "fork"
        host = roles.fork_host(AGENT_MODULES, logs / f"{HOST}.log") if fork and remote is None else None
        if not routers:
            wait_listening(port, starting_s, lambda: roles.roles["dmo"].process.poll() is None)
        if cluster:
            cluster.check_reaches(port)
        if view is not None:  # before the DMO's first message, which waits for the recorder started below
            view.start(run_id, local, auth, logs, Path(private))
        observer_config = BusConfig(mode="client", connect=(local,), overrides=bundle_settings(auth, OBSERVER))
        with Bus(run_id, OBSERVER, observer_config, announce=False) as observer:
            watch = _Watch(roles, faults, say, tick)
            observer.subscribe(observer.keys.clock(), watch.on_clock)
            observer.subscribe(observer.keys.schedule("*"), watch.on_schedule)
            if record:
                # The DMO waits for the recorder before its first message; the agents start once that message is
                # out, so the recording has the run from its first message.
                roles.start("recorder", dmosim_command(
                    "record", "--out", str(record), "--run-id", run_id, "--overwrite", "--connect", local,
                    *login, *_recording_metadata(e, fleet, rundir)), log=logs / "recorder.log")
                _wait_until(watch.started, roles, ("dmo", "recorder"), 1.5 * starting_s, "the DMO's first message")
            router_of = spread([m.id for m in fleet], len(routers)) if routers else {}
            agents = [(m.id, ["agent", *common, "--id", m.id, "--connect",
                              routers[router_of[m.id]] if routers else reach, "--lease", repr(AGENT_LEASE_S)],
                       (logs / f"{m.id}.log").resolve()) for m in fleet]
            if remote is None:
                alone = {f.agent for f in faults}  # killed or restarted: the fault must reach that agent only
                for group in groups(agents, per_process if host is not None else 1, alone):
                    commands = [(name, dmosim_command(*args, *login), log) for name, args, log in group]
                    if len(commands) > 1:
                        roles.start_group(host, commands)
                    else:
                        roles.start(commands[0][0], commands[0][1], log=commands[0][2], host=host)
            else:
                placed = remote.start(agents, {m.id: read_bundle(auth, m.id) for m in fleet},
                                      AGENT_MODULES if fork else None,
                                      lambda i: (logs / f"{HOST}-{i + 1}.log").resolve())
                say(f"agents on {len(placed)} worker(s): "
                    + "; ".join(f"{w}: {', '.join(names)}" for w, names in placed.items()))
            failed = wait_for_run(roles, watch, remote=remote.names if remote else (), routers=names)
        if failed:
            raise RoleFailed(failed, roles, logs)
        recorder = _stop_recorder(roles, watch, faults, record) if record else None
        restarts = {name: r.restarts for name, r in roles.roles.items() if r.restarts}
    result = read_result(rundir.result, DmoReport)  # the DMO's, as its process wrote it
    launched = {"wall_s": round(time.monotonic() - began, 3),
                "memory_mib": {str(day): roles_memory for day, roles_memory in sorted(watch.memory.items())},
                "experiment": e.name, "run_dir": str(rundir.root.resolve()), "logs": str(logs.resolve()),
                "recording": str(record.resolve()) if record else None, "faults": [str(f) for f in parsed],
                "restarts": restarts}
    if routers:  # which router each role was told to connect to
        launched["routers"] = Routers(endpoints=dict(zip(names, routers)), roles={
            "dmo": names[0], **({"recorder": names[0]} if record else {}),
            **{m.id: names[router_of[m.id]] for m in fleet}})
    if remote is not None:
        launched["cluster"] = Placement(scheduler=cluster.address, dmo=reach, agents=remote.placed)
    return concluded(result, launched, e, fleet, run_id, rundir, record, recorder, repeat_of, say)


def concluded(result: DmoReport, launched: dict, e: Experiment, fleet: list[FleetMember], run_id: str,
              rundir: RunDir, record: Path | None, recorder: str | None = None, repeat_of: str | Path | None = None,
              say: Callable[[str], None] = lambda text: None) -> RunReport:
    """The DMO's ``result`` with what the launcher adds (``launched``: the fields of ``RunReport`` it knows), concluded:
    what the recording holds, its tables and figure, its re-settlement, the comparison with the run it repeats, and
    the verdict, written to the run directory. ``recorder``: how the recorder failed (None: it did not)."""
    # What the run said, as a recording: the recording itself when it is complete, else the DMO's journal.
    rec, complete, recorded, reproduced, written = None, False, None, None, {}
    if record:
        rec, recorded = _recorded(record, recorder)
        complete = recorded.complete
    if record or repeat_of is not None:
        said = rec if complete else journal_recording(rundir.logs / "dmo.journal", run_id, _run_metadata(e, fleet))
        if repeat_of is not None:
            reproduced = reproduction(repeat_of, said, say)
        if record and said.messages:
            recorded = recorded.model_copy(update={"tables_from": "recording" if complete else "journal"})
            say("writing the run's tables and figure" + ("" if complete else " from the DMO's journal (the "
                                                                               "recording is incomplete)"))
            written = _write_results(said, rundir, run_id)
    if complete:
        recorded = recorded.model_copy(update={"resettled": resettled(rec, [d.market_day for d in result.days], e)})
    found = problems(result, agents=[m.id for m in fleet], days=e.days,
                     recorded=set(statements_of(rec)) if complete else None, recording=recorded, reproduced=reproduced)
    report = RunReport.model_validate({**dict(result), **launched, "recorded": recorded, "reproduced": reproduced,
                                       **written, "verdict": verdict(found)})
    rundir.result.write_text(result_text(report) + "\n")
    return report


def _remote(cluster: Cluster | None, run_id: str, roles: Roles) -> RemoteAgents | contextlib.nullcontext:
    """The run's agents on the cluster's workers, stopped on leaving; without a cluster, nothing."""
    return RemoteAgents(cluster, run_id, roles.exits) if cluster else contextlib.nullcontext()


def reproduction(source: str | Path, again: Recording, say: Callable[[str], None] = lambda text: None) -> Reproduced:
    """Whether the run (``again``: what it said) settled every agent as the recording ``source`` it was repeated
    from; where not, which agent, day and hour differ (a fault, a missed deadline or a solve cut by its time limit
    can make a run differ)."""
    try:
        before = read_recording(source)
    except RecordingError as exc:
        return Reproduced(source=str(source), identical=False, differences=[], error=str(exc))
    diffs = differences(before, again)
    if diffs:
        say(f"{len(diffs)} statement line(s) differ from {source}:")
        for line in diffs:
            say(f"  {line}")
    else:
        say(f"every statement is the same as in {source}, to the cent")
    return Reproduced(source=str(source), identical=not diffs, differences=diffs)


def _run_metadata(experiment: Experiment, fleet: list[FleetMember]) -> dict[str, str]:
    """What the recording's metadata says of the run: the resolved experiment, seed, market day, days, agents."""
    return {"config": json.dumps(experiment.model_dump(), sort_keys=True), "seed": str(experiment.seed),
            "market_day": experiment.market_day, "days": str(experiment.days),
            "agents": ",".join(m.id for m in fleet), "command": "dmosim run"}


def _recording_metadata(experiment: Experiment, fleet: list[FleetMember], rundir: RunDir) -> list[str]:
    """The recorder's --meta and --attach flags (``recording_inputs``)."""
    meta, paths = recording_inputs(experiment, fleet, rundir)
    flags = [flag for k, v in meta.items() for flag in ("--meta", f"{k}={v}")]
    return flags + [flag for path in paths for flag in ("--attach", path)]


def recording_inputs(experiment: Experiment, fleet: list[FleetMember], rundir: RunDir) -> tuple[dict, list[str]]:
    """What a recording of the run holds besides its messages: the run's metadata, and the files it attaches (the
    resolved experiment, so that the recording can be run again, the case and fleet files)."""
    meta = _run_metadata(experiment, fleet)
    fleet_file = rundir.logs / "fleet.toml"
    fleet_file.write_text("".join(f"[[agents]]\nid = {json.dumps(m.id)}\ncase = {json.dumps(m.case)}\n"
                                  f"scale = {m.scale!r}\nshift_hours = {m.shift_hours}\nseed = {m.seed}\n"
                                  + (f"strategy = {json.dumps(m.strategy)}\n" if m.strategy else "")
                                  + (f"bus = {json.dumps(m.bus)}\n" if m.bus else "") + "\n"
                                  for m in fleet))
    cases = sorted({str(p) for p in map(case_path, [experiment.market.case, *(m.case for m in fleet)]) if p.is_file()})
    feeder = experiment.network.feeder
    cases += [feeder] if feeder is not None and Path(feeder).is_file() else []  # a network file goes with its run
    return meta, [str(rundir.experiment), *cases, str(fleet_file)]


def _write_results(rec: Recording, rundir: RunDir, run_id: str) -> dict:
    """The run's recording as tables (``dmosim export``) and a figure (``dmosim plot``) in the run directory."""
    from dmosim.studies.figures import save  # noqa: PLC0415  (pandas, matplotlib: only once a run is over)

    from ..results.figures import figure_of  # noqa: PLC0415
    from ..results.tables import tables, write_tables  # noqa: PLC0415

    frames = tables(rec)
    rundir.tables.mkdir(exist_ok=True)
    written = {"tables": {path.stem: str(path.resolve()) for path in write_tables(frames, rundir.tables)}}
    if not frames["hours"].empty:
        save(figure_of(rec, frames, f"run {run_id}"), rundir.figure)
        written["figure"] = str(rundir.figure.resolve())
    return written


def _wait_until(event: threading.Event, roles: Roles, watched: tuple[str, ...], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not event.wait(0.1):
        for name in watched:
            if roles.roles[name].process.poll() is not None:
                raise RuntimeError(f"{name} exited before {what}; its log: {roles.roles[name].log}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"no sign of {what} within {timeout_s:g} s")


def _stop_recorder(roles: Roles, watch: _Watch, faults: list[Fault], path: Path) -> str | None:
    """SIGTERM the recorder once the run is over: it writes its last chunk, the summary and the footer to ``path``.
    None if it did all that (a recorder that finished its file but did not exit cleanly is killed and logged, its
    file trusted); else its failure in one line: killed by a fault, exited before the run ended, or failed to finish
    its file."""
    role = roles.roles["recorder"]
    process = role.process
    time.sleep(0.2)  # what the DMO sent last is still on its way to the recorder
    if process.poll() is not None:
        at = f" at {watch.recorder_exit}" if watch.recorder_exit else " before it was stopped"
        if role.killed_on_purpose:
            spec = next((str(f) for f in faults if f.agent == "recorder"), "")
            return f"killed{at} (--fault {spec})"
        return f"exited{at} ({_exit_status(process.returncode, role.log)}; its log: {role.log})"
    process.send_signal(signal.SIGTERM)
    try:
        code = process.wait(timeout=RECORDER_STOP_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        code = None
    if code == 0:
        return None
    if _finished(path):  # it wrote its footer and then failed to leave: what it recorded is whole
        left = "did not exit and was killed" if code is None else f"ended {_exit_status(code)}"
        watch.say(f"the recorder finished its file but then {left} (its log: {role.log})")
        return None
    if code is None:
        return f"did not finish its file within {RECORDER_STOP_S:g} s of being stopped (its log: {role.log})"
    return f"failed to finish its file ({_exit_status(code, role.log)}; its log: {role.log})"


def _finished(path: Path) -> bool:
    """Whether the recording at ``path`` is whole: its summary and footer written."""
    try:
        return read_recording(path).complete
    except RecordingError:
        return False


def _exit_status(code: int, log: Path | None = None) -> str:
    """How a process ended: the signal that killed it, or its exit code and, if it failed, the last line of its
    ``log`` (a failing dmosim role's last line is its error)."""
    if code < 0:
        return f"killed by {signal.Signals(-code).name}"
    lines = log.read_text(errors="replace").split("\n") if code and log and log.exists() else []
    last = next((line.strip() for line in reversed(lines) if line.strip()), "")
    return f"exit {code}" + (f": {last[:300]}" if last else "")


def _recorded(path: Path, recorder: str | None) -> tuple[Recording | None, Recorded]:
    """The recording read back, and what the result says of it: its counts, whether it is ``complete`` (the file
    whole and the recorder never failed) and the ``recorder``'s failure (None if none)."""
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        return None, Recorded(error=str(exc), complete=False, recorder=recorder)
    return rec, Recorded(messages=len(rec.messages), channels=len(rec.channels), bytes=rec.size,
                         complete=rec.complete and recorder is None, recorder=recorder)


def resettled(rec: Recording, days: list[str], e: Experiment) -> Resettled:
    """The settled ``days`` re-settled from the recording alone, as ``dmosim settle`` would, and compared with the
    statements the DMO published: ``identical`` and the ``differences`` (one line each, after the market day), or
    the ``error`` that kept a day from being re-settled. The rule the experiment named is trusted; no other is."""
    trust = Trust.of(False, [e.market.settlement] if e.market.settlement else [])
    try:
        found = resettled_differences(rec, days, trust)
    except UntrustedRule as exc:
        return Resettled(identical=False, error=f"the recording names the rule {exc.spec}, not the experiment's")
    except ValueError as exc:
        return Resettled(identical=False, error=str(exc))
    return Resettled(identical=not found, differences=found)


def wait_for_run(roles: Roles, watch: _Watch, leave_s: float = 60.0, remote: Iterable[str] = (),
                 routers: Iterable[str] = ()) -> list[str]:
    """Block on process exits until the DMO is done and the agents have left; return the names that failed.
    ``remote`` names agents that are not among ``roles`` (on a cluster's workers) whose exits come on ``roles.exits``
    all the same.

    An agent that exits non-zero on its own stops the run. One killed on purpose is the DMO's problem: the day
    goes on and settles it by the missing-data rule. Once the DMO is done, the agents have ``leave_s`` to leave;
    one still there has failed, unless it was restarted on purpose: its restart came after the run had ended (a
    fault fires when the launcher sees the clock reach its hour, which a fast day may have passed by then), and
    what it did before is settled, so it is stopped. The recorder is an observer: whenever it exits, the run goes
    on (the DMO needs it only before its first message) and ``watch.recorder_exit`` notes when. The run's own
    ``routers`` (``--routers``) stay up to the end: one that exits fails the run.
    """
    routers = set(routers)
    pending = set(roles.roles) - {"recorder", *routers} | set(remote)
    while pending:
        timeout = leave_s if "dmo" not in pending else None
        try:
            name, code = roles.exits.get(timeout=timeout)
        except queue.Empty:
            late = sorted(n for n in pending if n in roles.roles and roles.roles[n].restarts)
            if late:
                watch.say(f"{', '.join(late)} restarted after the run had ended: stopped")
            return sorted(pending - set(late))
        if name == "recorder":
            watch.recorder_exit = watch.killed_at.get("recorder") or watch.when()
            watch.say(f"the recorder exited at {watch.recorder_exit} ({_exit_status(code)}); the run goes on, and "
                      "its tables will come from the DMO's journal")
            continue
        if name in routers:  # the run's routers stay up to the end: one that exits has failed
            return [name]
        pending.discard(name)
        if code != 0 and not (name in roles.roles and roles.roles[name].killed_on_purpose):
            return [name]
    return []


def progress_of(clock: Clock) -> tuple[int, int, str, tuple[int, str, int | None]]:
    """Where a clock message says the run is: hours done, hours in all, in words, and as (day, phase, hour), which
    ``dmosim.console.Mark`` takes with the time it was seen."""
    done = HOURS * clock.day if clock.phase == "settlement" else HOURS * (clock.day - 1) + (clock.hour or 1) - 1
    day = f"day {clock.day}/{clock.days}, " if clock.days > 1 else ""
    return (done, HOURS * clock.days, f"{day}phase {clock.phase}" + (f", hour {clock.hour}/24" if clock.hour else ""),
            (clock.day, clock.phase, clock.hour))


class _Watch:
    """What the run shows of the DMO's clock and the agents' schedules, and the process faults it fires on the clock.

    Scheduling can take minutes: each agent is shown as its schedule arrives, with the seconds since the awards
    went out (the clock's ``scheduling`` step) and its solve's status and certified gap."""

    def __init__(self, roles: Roles, faults: list[Fault], say: Callable[[str], None],
                 tick: Callable[[int, int, str], None] | None = None):
        self.roles, self.faults, self.say = roles, faults, say
        self.tick = tick or (lambda done, total, text, mark=None: say(text))
        self.hours = (0, 1)  # hours of the run done, and in all, as the DMO's clock last said
        self.started = threading.Event()
        self.lock = threading.Lock()
        self.fired: set[Fault] = set()
        self.scheduling_since: float | None = None
        self.day = ""
        self.clock = "the start"  # where the DMO's clock stands, as the run's messages say it
        self.recorder_exit: str | None = None  # where it stood when the recorder exited
        self.killed_at: dict[str, str] = {}  # role -> where the clock stood when a fault killed it
        # day -> role -> its memory as the day's last hour starts, when every agent is still there; a role already
        # gone by then keeps its latest sample (docs/experiments.md, "The result": `memory_mib`)
        self.memory: dict[int, dict[str, dict]] = {}

    def when(self) -> str:
        with self.lock:
            return self.clock

    def on_clock(self, key, msg: Clock, received_at) -> None:
        self.started.set()
        with self.lock:
            self.day = f"day {msg.day}/{msg.days}, " if msg.days > 1 else ""
            self.clock = f"day {msg.day} {msg.phase}" + (f" hour {msg.hour}" if msg.hour else "")
            self.scheduling_since = time.monotonic() if msg.phase == "scheduling" else None
            done, total, text, mark = progress_of(msg)
            self.hours = (done, total)
            self.tick(done, total, text, mark)
            for f in self.faults:
                if msg.phase == "realtime" and (msg.day, msg.hour) == (f.day, f.hour) and f not in self.fired:
                    self.fired.add(f)
                    self._fire(f)
            if msg.phase == "realtime" and msg.hour in (1, HOURS - 1, HOURS):  # after the faults: they must not wait
                self.memory[msg.day] = self.memory.get(msg.day, {}) | roles_memory(self.roles)  # see self.memory

    def on_schedule(self, key, msg: Schedule, received_at) -> None:
        with self.lock:
            since = self.scheduling_since
            took = f" in {time.monotonic() - since:.1f} s" if since is not None else ""
            gap = f", gap {100 * msg.mip_gap:.2f}%" if msg.mip_gap is not None else ""
            self.tick(*self.hours, f"{self.day}{msg.sender} scheduled{took} ({msg.status}{gap}, {msg.scenarios} scenario(s), "
                     f"expected cost ${msg.expected_cost:,.2f})")

    def _fire(self, f: Fault) -> None:
        when = f"hour {f.hour} of day {f.day}"
        if f.agent not in self.roles.roles:
            self.say(f"fault {f}: this run has no {f.agent}")
        elif f.kind == "restart" and f.agent == "dmo":
            self.say(f"fault: restarting the DMO (SIGKILL, then start again) {DMO_KILL_AFTER_S:g} s into {when}")
            recorder, dmo = self.roles.roles.get("recorder"), self.roles.roles["dmo"]
            if recorder is not None and recorder.process.poll() is not None and AWAIT_RECORDER in dmo.argv:
                at = dmo.argv.index(AWAIT_RECORDER)  # the recorder is gone: the DMO must not wait for it again
                dmo.argv = dmo.argv[:at] + dmo.argv[at + 2:]
            threading.Timer(DMO_KILL_AFTER_S, self.roles.restart, ("dmo",)).start()
        elif f.kind == "restart":
            self.say(f"fault: restarting {f.agent} (SIGKILL, then start again) at {when}")
            self.roles.restart(f.agent)
        else:
            self.say(f"fault: killing {f.agent} (SIGKILL) at {when}")
            self.killed_at[f.agent] = self.clock  # where it died, whenever its exit is seen
            self.roles.kill(f.agent)
