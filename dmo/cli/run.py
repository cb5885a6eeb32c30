"""``dmosim run``: a whole market day as separate OS processes (the DMO, one per agent, the recorder) over Zenoh,
on this machine: credentials made for the run, the roles started and watched (launch/), faults injected, and the
day's settlement printed with its recording."""

from __future__ import annotations

import argparse
import json
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from messages import Clock
from messages.keys import new_run_id
from messages.recording import RecordingError, read_recording
from messages.transport import Bus, BusConfig
from messages.transport.access import AuthError, bundle_settings
from messages.transport.credentials import create_auth_dir
from messages.transport.faults import FaultSpecError, MessageFault
from scenarios.case import case_path, load_case
from scenarios.fleet import FleetError, load_fleet, make_fleet

from ..launch.faults import Fault, parse_fault
from ..launch.processes import Roles, dmosim_command, free_port, wait_listening
from .console import UsageError, print_json, progress
from .flags import add_agent_flags, add_day_flags, positive_int, recording_path, today

HELP = "a whole market day: the DMO and one process per agent over Zenoh"
FAULT_HELP = ("a fault to inject (repeatable; docs/faults.md): kill:AGENT:HOUR (SIGKILL the agent when the clock "
              "reaches HOUR), restart:AGENT:HOUR (SIGKILL it, then start it again: it rejoins; AGENT may be dmo: it "
              "resumes the day from its journal), and on the messages "
              "whose key, relative to the run prefix, matches PATTERN (* one level, ** any, e.g. agent/*/meter): "
              "drop:PATTERN:P, duplicate:PATTERN:P, corrupt:PATTERN:P (each with probability P) and "
              "delay:PATTERN:SECONDS[:P]; seeded by --seed")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--agents", type=positive_int, default=3, help="number of agents mg1..mgN (default: 3)")
    p.add_argument("--fleet", help="fleet TOML file naming the agents and their cases (overrides --agents)")
    add_day_flags(p)
    add_agent_flags(p)
    p.add_argument("--fault", action="append", default=[], metavar="SPEC", help=FAULT_HELP)
    p.add_argument("--check", action="store_true",
                   help="check the inputs (case, fleet, faults, recording path) and exit without running")
    p.add_argument("--logs", help="directory for the roles' logs and result (default: a new temporary one)")
    record = p.add_mutually_exclusive_group()
    record.add_argument("--record", metavar="PATH", help="the day's MCAP recording (default: LOGS/day.mcap)")
    record.add_argument("--no-record", action="store_true", help="run without a recorder")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording at --record PATH")
    p.add_argument("--json", action="store_true", help="print one JSON object (README, \"Commands\")")
    p.add_argument("--tls", action="store_true",
                   help="also connect the roles over mutual TLS with certificates made for this run (the per-run "
                        "passwords and access control are always on; docs/security.md)")




def run(args) -> int:
    try:
        fleet = load_fleet(args.fleet) if args.fleet else make_fleet(args.agents, seed=args.seed)
    except FleetError as exc:
        raise UsageError(str(exc)) from None
    try:
        parsed = [parse_fault(f) for f in args.fault]
    except FaultSpecError as exc:
        raise UsageError(f"--fault: {exc}") from None
    faults = [f for f in parsed if isinstance(f, Fault)]
    # every role gets the message faults and applies those that match what it publishes
    message_faults = [flag for f in parsed if isinstance(f, MessageFault) for flag in ("--fault", str(f))]
    message_faults += ["--fault-seed", str(args.seed)] if message_faults else []
    unknown = sorted({f.agent for f in faults} - {m.id for m in fleet} - {"dmo"})
    if any(f.agent == "dmo" and f.kind != "restart" for f in faults):
        raise UsageError("--fault: the DMO can only be restarted (restart:dmo:HOUR), not killed")
    if unknown:
        raise UsageError(f"--fault names unknown agent {unknown[0]} (agents: {', '.join(m.id for m in fleet)})")
    if args.check:
        for name in sorted({args.case, *(m.case for m in fleet)}):
            load_case(name)  # a bad case is a CaseError: one line, exit 2
        if args.record:
            recording_path(args.record, args.overwrite)
        print(f"dmosim run: inputs are valid: {len(fleet)} agents ({', '.join(m.id for m in fleet)}), case "
              f"{args.case}, {len(parsed)} fault(s)")
        return 0

    run_id = new_run_id()
    port = free_port()
    endpoint = f"{'tls' if args.tls else 'tcp'}/127.0.0.1:{port}"
    if args.record:
        recording = recording_path(args.record, args.overwrite)  # before anything starts: a bad path is exit 2
    logs = Path(args.logs) if args.logs else Path(tempfile.mkdtemp(prefix=f"dmosim-{run_id}-"))
    logs.mkdir(parents=True, exist_ok=True)
    if not args.record:
        recording = None if args.no_record else recording_path(str(logs / "day.mcap"), True)
    result_path = logs / "result.json"
    auth = _credentials(logs / "auth", run_id, fleet, args.tls)
    market_day = args.market_day or today()
    day = ["--run-id", run_id, "--market-day", market_day]
    _say(args, f"run {run_id}: DMO and {len(fleet)} agents on {endpoint}; logs in {logs}"
               + (f"; recording to {recording}" if recording else "; not recording"))

    signal.signal(signal.SIGTERM, _interrupt)  # a terminated run stops its roles like Ctrl-C does
    with Roles() as roles:
        roles.start("dmo", dmosim_command("dmo", *day, "--listen", endpoint, "--agents", str(len(fleet)),
                                   "--case", args.case, "--market", args.market, "--seed", str(args.seed),
                                   "--island-hours", str(args.island_hours), "--result", str(result_path),
                                   "--journal", str(logs / "dmo.journal"),
                                   "--subperiods", str(args.subperiods),
                                   *(["--await-recorder", "60"] if recording else []),
                                   *_opt("--penalty", args.penalty), *_deadlines(args), "--auth-dir", str(auth),
                                   *message_faults),
                    log=logs / "dmo.log")
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        observer_config = BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, OBSERVER))
        with Bus(run_id, OBSERVER, observer_config, announce=False) as observer:
            started = threading.Event()
            observer.subscribe(observer.keys.clock(), _watch_clock(args, roles, faults, started))
            if recording:
                # The DMO waits for the recorder before its first message; the agents start once that message
                # is out, so the recording has the day from its first message.
                roles.start("recorder", dmosim_command("record", "--out", str(recording), "--run-id", run_id, "--overwrite",
                                                "--connect", endpoint, "--auth-dir", str(auth),
                                                *_recording_metadata(args, fleet, market_day, logs)),
                            log=logs / "recorder.log")
                _wait_until(started, roles, ("dmo", "recorder"), 90, "the DMO's first message")
            for m in fleet:
                roles.start(m.id, dmosim_command("agent", *day, "--id", m.id, "--connect", endpoint, "--case", m.case,
                                          "--scale", repr(m.scale), "--shift-hours", str(m.shift_hours),
                                          "--seed", str(m.seed), "--scenarios", str(args.scenarios),
                                          "--island-hours", str(args.island_hours), "--gap", repr(args.gap),
                                          "--time-limit", repr(args.time_limit), "--method", args.method,
                                          "--workers", str(args.workers), "--lease", "1",
                                          "--auth-dir", str(auth), *message_faults),
                            log=logs / f"{m.id}.log")
            failed = _wait_for_day(roles)
        if recording and not failed:
            failed = _stop_recorder(roles)
        if failed:
            for name in failed:
                _say(args, f"{name} failed; its log: {roles.roles[name].log}")
                _tail(roles.roles[name].log)
            return 1
    result = json.loads(result_path.read_text())
    result["recording"] = str(recording.resolve()) if recording else None
    if recording:
        result["recorded"] = _recorded(recording)
    result["logs"] = str(logs)
    result["faults"] = [str(f) for f in parsed]
    result["restarts"] = {name: r.restarts for name, r in roles.roles.items() if r.restarts}
    if args.json:
        print_json(result)
    else:
        print(summary_table(result))
    return 0


OBSERVER = "run"  # the name this process watches the day's clock under


def _credentials(out: Path, run_id: str, fleet, tls: bool) -> Path:
    """Fresh credentials for every role of this run (messages/security.py), so the default day authenticates each
    process and the DMO's router enforces its access control with no configuration at all."""
    try:
        return create_auth_dir(out, run_id, [m.id for m in fleet], readers=("recorder", OBSERVER), tls=tls,
                               valid_days=2, dmo_client=False, overwrite=True)  # the DMO is the router
    except AuthError as exc:
        raise UsageError(f"cannot make the run's credentials: {exc}") from None


def _recording_metadata(args, fleet, market_day: str, logs: Path) -> list[str]:
    """The recorder's --meta and --attach flags: the run's configuration, seed, market day, agents and versions
    (the recorder adds its own), the case files and the fleet (a fleet file, or the generated fleet as one)."""
    config = {k: v for k, v in sorted(vars(args).items()) if k not in ("run", "json", "quiet")}
    meta = {"config": json.dumps(config, sort_keys=True, default=str), "seed": str(args.seed),
            "market_day": market_day, "agents": ",".join(m.id for m in fleet), "command": "dmosim run"}
    if args.fleet:
        fleet_file = Path(args.fleet)
    else:
        fleet_file = logs / "fleet.toml"
        fleet_file.write_text("".join(f"[[agents]]\nid = {json.dumps(m.id)}\ncase = {json.dumps(m.case)}\n"
                                      f"scale = {m.scale!r}\nshift_hours = {m.shift_hours}\nseed = {m.seed}\n\n"
                                      for m in fleet))
    cases = sorted({str(p) for p in map(case_path, [args.case, *(m.case for m in fleet)]) if p.is_file()})
    flags = [flag for k, v in meta.items() for flag in ("--meta", f"{k}={v}")]
    return flags + [flag for path in [*cases, str(fleet_file)] for flag in ("--attach", path)]


def _wait_until(event: threading.Event, roles: Roles, watched: tuple[str, ...], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not event.wait(0.1):
        for name in watched:
            if roles.roles[name].process.poll() is not None:
                raise RuntimeError(f"{name} exited before {what}; its log: {roles.roles[name].log}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"no sign of {what} within {timeout_s:g} s")


def _stop_recorder(roles: Roles) -> list[str]:
    """SIGTERM the recorder once the day is over: it writes its last chunk, the summary and the footer."""
    process = roles.roles["recorder"].process
    time.sleep(0.2)  # what the DMO sent last is still on its way to the recorder
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        code = process.wait(timeout=60)
    except subprocess.TimeoutExpired:
        return ["recorder"]
    return [] if code == 0 else ["recorder"]


def _recorded(path: Path) -> dict:
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        return {"error": str(exc)}
    return {"messages": len(rec.messages), "channels": len(rec.channels), "bytes": rec.size,
            "complete": rec.complete}


def _interrupt(*_):
    raise KeyboardInterrupt


def _wait_for_day(roles: Roles) -> list[str]:
    """Block on process exits until the DMO is done and the agents have left; return the names that failed.

    An agent that exits non-zero on its own stops the run. One killed on purpose is the DMO's problem: the day
    goes on and settles it by the missing-data rule. The recorder runs until it is stopped: any exit of its own
    is a failure.
    """
    pending = set(roles.roles) - {"recorder"}
    failed = []
    while pending:
        timeout = 60.0 if "dmo" not in pending else None  # once the day is settled, agents get a minute to leave
        try:
            name, code = roles.exits.get(timeout=timeout)
        except queue.Empty:
            return failed + sorted(pending)
        pending.discard(name)
        if name == "recorder" or (code != 0 and not roles.roles[name].killed_on_purpose):
            return failed + [name]
    return failed


def _watch_clock(args, roles: Roles, faults: list[Fault], started: threading.Event):
    lock = threading.Lock()
    fired: set[Fault] = set()

    def on_clock(key, msg: Clock, received_at):
        started.set()
        with lock:
            _say(args, f"phase {msg.phase}" + (f", hour {msg.hour}/24" if msg.hour else ""))
            for f in faults:
                if msg.phase != "realtime" or msg.hour != f.hour or f in fired:
                    continue
                fired.add(f)
                if f.kind == "restart" and f.agent == "dmo":
                    # mid-hour: the agents' answers are on their way when it dies, and must not be lost
                    _say(args, f"fault: restarting the DMO (SIGKILL, then start again) {DMO_KILL_AFTER_S:g} s into "
                               f"hour {f.hour}")
                    threading.Timer(DMO_KILL_AFTER_S, roles.restart, ("dmo",)).start()
                elif f.kind == "restart":
                    _say(args, f"fault: restarting {f.agent} (SIGKILL, then start again) at hour {f.hour}")
                    roles.restart(f.agent)
                else:
                    _say(args, f"fault: killing {f.agent} (SIGKILL) at hour {f.hour}")
                    roles.kill(f.agent)

    return on_clock


DMO_KILL_AFTER_S = 0.5


def _opt(flag: str, value) -> list[str]:
    return [] if value is None else [flag, repr(value) if isinstance(value, float) else str(value)]


def _deadlines(args) -> list[str]:
    return ["--registration-timeout", repr(args.registration_timeout), "--bid-timeout", repr(args.bid_timeout),
            "--schedule-timeout", repr(args.schedule_timeout), "--hour-timeout", repr(args.hour_timeout)]


def _say(args, text: str) -> None:
    if not args.quiet:
        progress(text)


def _tail(path: Path | None, lines: int = 15) -> None:
    if path and path.exists():
        for line in path.read_text(errors="replace").splitlines()[-lines:]:
            print(f"    {line}", file=sys.stderr)


def summary_table(result: dict) -> str:
    """Per agent: award energy, realised import, deviation energy, energy charge, penalty and total."""
    head = f"{'agent':<8}{'award MWh':>11}{'import MWh':>12}{'dev. MWh':>10}{'energy $':>12}{'penalty $':>11}{'total $':>12}"
    rows = [f"market day {result['market_day']}, run {result['run_id']}", head, "-" * len(head)]
    for agent, s in sorted(result["settlement"].items()):
        rows.append(f"{agent:<8}{s['award_mwh']:>11.2f}{s['import_mwh']:>12.2f}{s['deviation_mwh']:>10.3f}"
                    f"{s['energy_charge']:>12,.2f}{s['deviation_penalty']:>11,.2f}{s['total']:>12,.2f}")
    rows.append(f"rejected messages: {result['rejected_messages']}; islanded hours: {result['islanded_hours'] or 'none'}")
    recorded = result.get("recorded") or {}
    if result.get("recording"):
        rows.append(f"recording: {result['recording']}" + (
            f" ({recorded['messages']} messages on {recorded['channels']} channels, {recorded['bytes']:,} bytes"
            f"{'' if recorded['complete'] else ', INCOMPLETE'})" if "messages" in recorded else
            f" ({recorded.get('error', 'unreadable')})"))
    else:
        rows.append("recording: none (--no-record)")
    for incident in result["incidents"]:
        where = incident["phase"] + (f" hour {incident['hour']}" if incident["hour"] else "")
        rows.append(f"incident [{where}] {incident['agent'] or '-'}: {incident['reason']}")
    return "\n".join(rows)
