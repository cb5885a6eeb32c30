"""``dmosim run``: a whole market day as separate OS processes (the DMO and one per agent) over Zenoh on loopback."""

from __future__ import annotations

import json
import queue
import signal
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

from messages import Clock
from messages.keys import new_run_id
from messages.transport import Bus, BusConfig
from scenarios.fleet import FleetError, load_fleet, make_fleet

from ..console import UsageError, print_json, progress
from ..processes import Roles, free_port, wait_listening
from .roles import today


@dataclass(frozen=True)
class Fault:
    """``kill:AGENT:HOUR``: SIGKILL the agent's process when the DMO's clock reaches that hour."""

    agent: str
    hour: int


def parse_fault(text: str) -> Fault:
    kind, _, rest = text.partition(":")
    if kind != "kill":
        raise UsageError(f"--fault {text!r}: unknown fault {kind!r} (supported: kill:AGENT:HOUR)")
    agent, _, hour = rest.partition(":")
    if not agent or not hour.isdigit() or not 1 <= int(hour) <= 24:
        raise UsageError(f"--fault {text!r}: expected kill:AGENT:HOUR with HOUR in 1..24")
    return Fault(agent, int(hour))


def _python(*args: str) -> list[str]:
    return [sys.executable, "-m", "dmo.cli", *args]


def run(args) -> int:
    try:
        fleet = load_fleet(args.fleet) if args.fleet else make_fleet(args.agents, seed=args.seed)
    except FleetError as exc:
        raise UsageError(str(exc)) from None
    faults = [parse_fault(f) for f in args.fault]
    unknown = sorted({f.agent for f in faults} - {m.id for m in fleet})
    if unknown:
        raise UsageError(f"--fault names unknown agent {unknown[0]} (agents: {', '.join(m.id for m in fleet)})")

    run_id = new_run_id()
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    logs = Path(args.logs) if args.logs else Path(tempfile.mkdtemp(prefix=f"dmosim-{run_id}-"))
    logs.mkdir(parents=True, exist_ok=True)
    result_path = logs / "result.json"
    day = ["--run-id", run_id, "--market-day", args.market_day or today()]
    _say(args, f"run {run_id}: DMO and {len(fleet)} agents on {endpoint}; logs in {logs}")

    signal.signal(signal.SIGTERM, _interrupt)  # a terminated run stops its roles like Ctrl-C does
    with Roles() as roles:
        roles.start("dmo", _python("dmo", *day, "--listen", endpoint, "--agents", str(len(fleet)),
                                   "--case", args.case, "--market", args.market, "--seed", str(args.seed),
                                   "--island-hours", str(args.island_hours), "--result", str(result_path),
                                   "--subperiods", str(args.subperiods),
                                   *_opt("--penalty", args.penalty), *_deadlines(args)),
                    log=logs / "dmo.log")
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        for m in fleet:
            roles.start(m.id, _python("agent", *day, "--id", m.id, "--connect", endpoint, "--case", m.case,
                                      "--scale", repr(m.scale), "--shift-hours", str(m.shift_hours),
                                      "--seed", str(m.seed), "--scenarios", str(args.scenarios),
                                      "--island-hours", str(args.island_hours), "--gap", repr(args.gap),
                                      "--time-limit", repr(args.time_limit), "--lease", "1"),
                        log=logs / f"{m.id}.log")
        with Bus(run_id, "run", BusConfig(mode="client", connect=(endpoint,)), announce=False) as observer:
            observer.subscribe(observer.keys.clock(), _watch_clock(args, roles, faults))
            failed = _wait_for_day(roles)
        if failed:
            for name in failed:
                _say(args, f"{name} failed; its log: {roles.roles[name].log}")
                _tail(roles.roles[name].log)
            return 1
    result = json.loads(result_path.read_text())
    result["recording"] = None
    result["logs"] = str(logs)
    result["faults"] = [f"kill:{f.agent}:{f.hour}" for f in faults]
    if args.json:
        print_json(result)
    else:
        print(summary_table(result))
    return 0


def _interrupt(*_):
    raise KeyboardInterrupt


def _wait_for_day(roles: Roles) -> list[str]:
    """Block on process exits until the DMO is done and the agents have left; return the names that failed.

    An agent that exits non-zero on its own stops the run. One killed on purpose is the DMO's problem: the day
    goes on and settles it by the missing-data rule.
    """
    pending = set(roles.roles)
    failed = []
    while pending:
        timeout = 60.0 if "dmo" not in pending else None  # once the day is settled, agents get a minute to leave
        try:
            name, code = roles.exits.get(timeout=timeout)
        except queue.Empty:
            return failed + sorted(pending)
        pending.discard(name)
        if code != 0 and not roles.roles[name].killed_on_purpose:
            return failed + [name]
    return failed


def _watch_clock(args, roles: Roles, faults: list[Fault]):
    lock = threading.Lock()

    def on_clock(key, msg: Clock, received_at):
        with lock:
            _say(args, f"phase {msg.phase}" + (f", hour {msg.hour}/24" if msg.hour else ""))
            for f in faults:
                if msg.phase == "realtime" and msg.hour == f.hour and not roles.roles[f.agent].killed_on_purpose:
                    _say(args, f"fault: killing {f.agent} (SIGKILL) at hour {f.hour}")
                    roles.kill(f.agent)

    return on_clock


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
    for incident in result["incidents"]:
        where = incident["phase"] + (f" hour {incident['hour']}" if incident["hour"] else "")
        rows.append(f"incident [{where}] {incident['agent'] or '-'}: {incident['reason']}")
    return "\n".join(rows)
