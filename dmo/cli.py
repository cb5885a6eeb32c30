"""The ``dmosim`` command line: parses flags, runs one command, maps bad input to exit 2 and failures to exit 1."""

from __future__ import annotations

import argparse
import math
import os
import sys

from microgrid_agent.routes import AUTO_BENDERS_SCENARIOS, METHODS
from scenarios.case import CaseError

from .bench import BENCHES
from .console import UsageError

EXIT_USAGE = 2
EXIT_FAILURE = 1


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would print the whole usage; one line is enough
        raise UsageError(f"{self.prog}: {message}")


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def hours(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 24:
        raise argparse.ArgumentTypeError(f"expected whole hours 0..24, got {text!r}")
    return value


def nonneg_float(text: str, allow_inf: bool = False) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text!r}") from None
    if math.isnan(value) or value < 0 or (math.isinf(value) and not allow_inf):
        raise argparse.ArgumentTypeError(f"expected a non-negative{' ' if not allow_inf else ' (or inf) '}number, got {text!r}")
    return value


def penalty(text: str) -> float:
    return nonneg_float(text, allow_inf=True)


def gap(text: str) -> float:
    value = nonneg_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a relative gap below 1 (e.g. 0.005), got {text!r}")
    return value


def add_instance_flags(p: argparse.ArgumentParser, scenarios: int) -> None:
    """The flags that define one scheduling instance, shared by ``solve`` and ``study``."""
    p.add_argument("--case", default="paper", help="built-in case name or path to a case TOML file (default: paper)")
    p.add_argument("--scenarios", type=positive_int, default=scenarios, help=f"scenarios after reduction (default: {scenarios})")
    p.add_argument("--sample-size", type=positive_int, default=None, help="scenarios sampled before reduction (default: 10x)")
    p.add_argument("--subperiods", type=positive_int, default=6, help="sub-periods per hour (default: 6, i.e. 10 minutes)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenario draws (default: 0)")
    p.add_argument("--gap", type=gap, default=0.005, help="relative MIP gap to reach (default: 0.005)")
    p.add_argument("--time-limit", type=nonneg_float, default=900.0, help="seconds per solve (default: 900)")
    p.add_argument("--cost-convention", choices=("real", "paper"), default="real",
                   help="real: energy costs x dt; paper: objective (1) as printed, no dt (see docs/model.md)")
    add_method_flags(p, workers=2)


def add_method_flags(p: argparse.ArgumentParser, workers: int) -> None:
    """How a stochastic schedule is solved, shared by ``solve``, ``study``, ``run`` and ``agent``."""
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="extensive: one MILP in HiGHS (the reference); benders: multi-cut decomposition "
                        f"(docs/solver.md); auto (default): benders from {AUTO_BENDERS_SCENARIOS} scenarios on")
    p.add_argument("--workers", type=positive_int, default=workers,
                   help=f"processes for the Benders subproblems (default: {workers})")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole parser, or with ``command`` one whose other heavy sub-commands have no flags (a faster start)."""
    parser = _Parser(prog="dmosim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    solve = sub.add_parser("solve", help="one stochastic day-ahead schedule of one microgrid")
    add_instance_flags(solve, scenarios=10)
    solve.add_argument("--island-hours", type=hours, default=1, help="islanding hours per scenario (default: 1)")
    solve.add_argument("--transfer-scale", type=nonneg_float, default=1.0, help="multiplier of the award P_sch (default: 1)")
    solve.add_argument("--penalty", type=penalty, default=None, help="$/MWh above the award, or inf (default: the case's)")
    solve.add_argument("--metrics", action="store_true", help="also compute VSS and EVPI (solves S + 2 more problems)")
    solve.add_argument("--json", action="store_true", help="print one JSON object (SPEC section 4)")
    solve.add_argument("--verbose", action="store_true", help="show the HiGHS log")
    solve.set_defaults(run="dmo.commands.solve:run")

    _add_market_commands(sub)
    # study and bench import the solver stack (seconds): their flags are built only when they are the command
    study = sub.add_parser("study", help="reproduce the paper's Table II and Figures 2-5")
    if command in (None, "study"):
        _add_study_flags(study)
    bench = sub.add_parser("bench", help="benchmarks: " + ", ".join(sorted(BENCHES)))
    if command in (None, "bench"):
        _add_bench_commands(bench)
    return parser


def _add_study_flags(study: argparse.ArgumentParser) -> None:
    from microgrid_agent.studies import STUDIES  # noqa: PLC0415  (the list of studies lives with them)

    study.add_argument("name", choices=sorted(STUDIES), help="which result")
    add_instance_flags(study, scenarios=10)
    study.add_argument("--out", default="out", help="directory for the CSV and PNG files (default: out)")
    study.set_defaults(run="dmo.commands.study:run")


def _add_bench_commands(bench: argparse.ArgumentParser) -> None:
    bench_sub = bench.add_subparsers(dest="bench", required=True, parser_class=_Parser)
    for name, module in sorted(BENCHES.items()):
        p = bench_sub.add_parser(name, help=_load(f"{module}:__doc__").splitlines()[0])
        _load(f"{module}:add_arguments")(p)
        p.add_argument("--json", action="store_true", help="print one JSON object")
        p.set_defaults(run="dmo.commands.bench:run", bench_module=module)


def market_day(text: str) -> str:
    import datetime as dt  # noqa: PLC0415

    try:
        return dt.date.fromisoformat(text).isoformat()
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a date YYYY-MM-DD, got {text!r}") from None


def _add_day_flags(p: argparse.ArgumentParser) -> None:
    """Settings of the day the DMO runs, shared by ``run`` and ``dmo``."""
    p.add_argument("--case", default="paper", help="case giving the ISO price, penalty and Table I awards (default: paper)")
    p.add_argument("--market", choices=("bids", "fixed"), default="bids",
                   help="bids: clear the agents' bids; fixed: award the case's Table I to every agent")
    p.add_argument("--island-hours", type=hours, default=1, help="hours the feeder is islanded during the day (default: 1)")
    p.add_argument("--penalty", type=nonneg_float, default=None, help="$/MWh above the award (default: the case's)")
    p.add_argument("--subperiods", type=positive_int, default=6, help="metering sub-periods per hour (default: 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the day (islanding, fleet) (default: 0)")
    p.add_argument("--market-day", type=market_day, default=None, help="the market day, YYYY-MM-DD (default: today)")
    for name, default, what in (("registration", 60.0, "registration"), ("bid", 600.0, "bids"),
                                ("schedule", 1800.0, "schedules"), ("hour", 300.0, "each hour's meter reports")):
        p.add_argument(f"--{name}-timeout", type=nonneg_float, default=default, metavar="S",
                       help=f"deadline for {what}, seconds (default: {default:g})")
    p.add_argument("--quiet", action="store_true", help="log warnings only")


def _add_agent_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenarios", type=positive_int, default=5, help="scenarios of each agent's schedule (default: 5)")
    p.add_argument("--gap", type=gap, default=0.01, help="relative MIP gap of each agent's schedule (default: 0.01)")
    p.add_argument("--time-limit", type=nonneg_float, default=600.0, help="seconds per agent solve (default: 600)")
    add_method_flags(p, workers=1)  # the agents of one machine share its cores


FAULT_HELP = ("a fault to inject (repeatable; docs/faults.md): kill:AGENT:HOUR (SIGKILL the agent when the clock "
              "reaches HOUR), restart:AGENT:HOUR (SIGKILL it, then start it again: it rejoins; AGENT may be dmo: it "
              "resumes the day from its journal), and on the messages "
              "whose key, relative to the run prefix, matches PATTERN (* one level, ** any, e.g. agent/*/meter): "
              "drop:PATTERN:P, duplicate:PATTERN:P, corrupt:PATTERN:P (each with probability P) and "
              "delay:PATTERN:SECONDS[:P]; seeded by --seed")


def _add_fault_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="message fault on what this process publishes: drop|duplicate|corrupt:PATTERN:P or "
                        "delay:PATTERN:SECONDS[:P] (repeatable; docs/faults.md)")
    p.add_argument("--fault-seed", type=int, default=0, help="seed of the fault draws (default: 0)")


def _add_market_commands(sub) -> None:
    from messages.transport import add_bus_arguments  # noqa: PLC0415

    run = sub.add_parser("run", help="a whole market day: the DMO and one process per agent over Zenoh")
    run.add_argument("--agents", type=positive_int, default=3, help="number of agents mg1..mgN (default: 3)")
    run.add_argument("--fleet", help="fleet TOML file naming the agents and their cases (overrides --agents)")
    _add_day_flags(run)
    _add_agent_flags(run)
    run.add_argument("--fault", action="append", default=[], metavar="SPEC", help=FAULT_HELP)
    run.add_argument("--check", action="store_true",
                     help="check the inputs (case, fleet, faults, recording path) and exit without running")
    run.add_argument("--logs", help="directory for the roles' logs and result (default: a new temporary one)")
    record = run.add_mutually_exclusive_group()
    record.add_argument("--record", metavar="PATH", help="the day's MCAP recording (default: LOGS/day.mcap)")
    record.add_argument("--no-record", action="store_true", help="run without a recorder")
    run.add_argument("--overwrite", action="store_true", help="replace an existing recording at --record PATH")
    run.add_argument("--json", action="store_true", help="print one JSON object (SPEC section 4)")
    run.add_argument("--tls", action="store_true",
                     help="also connect the roles over mutual TLS with certificates made for this run (the per-run "
                          "passwords and access control are always on; docs/security.md)")
    run.set_defaults(run="dmo.commands.run:run")

    dmo = sub.add_parser("dmo", help="the market operator role alone (the Zenoh router by default)")
    dmo.add_argument("--agents", type=positive_int, required=True, help="agents to wait for at registration")
    dmo.add_argument("--run-id", default="day", help="key prefix shared with the agents (default: day)")
    _add_day_flags(dmo)
    dmo.add_argument("--credit", type=nonneg_float, default=0.0, help="$/MWh credited below the award (default: 0)")
    dmo.add_argument("--import-limit", type=nonneg_float, default=None, help="feeder import limit, MW (default: 8 x agents)")
    dmo.add_argument("--export-limit", type=nonneg_float, default=None, help="feeder export limit, MW (default: 5 x agents)")
    dmo.add_argument("--result", help="write the day's JSON result here (default: stdout)")
    dmo.add_argument("--journal", metavar="PATH",
                     help="journal the day here; a DMO restarted with the same journal, run id and market day "
                          "resumes the day from it (docs/faults.md)")
    dmo.add_argument("--await-recorder", type=nonneg_float, default=0.0, metavar="S",
                     help="wait up to S seconds for a recorder of this run before the first message (default: 0, "
                          "do not wait)")
    _add_fault_flags(dmo)
    add_bus_arguments(dmo)
    dmo.set_defaults(run="dmo.commands.roles:run_dmo")

    agent = sub.add_parser("agent", help="one microgrid agent role")
    agent.add_argument("--id", required=True, help="agent id, e.g. mg1")
    agent.add_argument("--run-id", default="day", help="key prefix shared with the DMO (default: day)")
    agent.add_argument("--case", default="paper", help="the microgrid's case (default: paper)")
    agent.add_argument("--scale", type=nonneg_float, default=1.0, help="size multiplier of the case (default: 1)")
    agent.add_argument("--shift-hours", type=int, default=0, help="shift of the load and renewable profiles (default: 0)")
    agent.add_argument("--seed", type=int, default=0, help="seed of the agent's scenarios and realised day")
    agent.add_argument("--island-hours", type=hours, default=1, help="islanding hours the schedule plans for (default: 1)")
    agent.add_argument("--market-day", type=market_day, default=None, help="the market day (default: today)")
    agent.add_argument("--idle-timeout", type=nonneg_float, default=3600.0, help="give up after this long without news")
    agent.add_argument("--quiet", action="store_true")
    _add_agent_flags(agent)
    _add_fault_flags(agent)
    add_bus_arguments(agent)
    agent.set_defaults(run="dmo.commands.roles:run_agent")

    _add_recording_commands(sub)

    router = sub.add_parser("router", help="a standalone Zenoh router for the DMO and agents to connect to")
    router.add_argument("--quiet", action="store_true")
    add_bus_arguments(router)
    router.set_defaults(run="dmo.commands.roles:run_router")

    creds = sub.add_parser("credentials", help="passwords, access-control rules and TLS certificates of one run, "
                                               "for roles on several hosts (docs/security.md)")
    creds.add_argument("--out", required=True, metavar="DIR", help="directory to create: the router's files, and "
                                                                   "one bundle DIR/<name>/ per other process")
    creds.add_argument("--run-id", default="day", help="the run the rules are for (default: day)")
    creds.add_argument("--agents", type=positive_int, default=3, help="agents mg1..mgN (default: 3)")
    creds.add_argument("--fleet", help="fleet TOML file naming the agents (overrides --agents)")
    creds.add_argument("--reader", action="append", default=[], metavar="NAME",
                       help="a process that may hear everything of the run and publish nothing (repeatable; "
                            "default: recorder)")
    creds.add_argument("--tls", action="store_true",
                       help="also make a CA and certificates: every process must then connect over tls/ endpoints "
                            "with its own certificate")
    creds.add_argument("--host", action="append", default=[], metavar="NAME",
                       help="host name or IP address the router's certificate is valid for (repeatable; default: "
                            "localhost and 127.0.0.1)")
    creds.add_argument("--days", type=positive_int, default=30, help="validity of the certificates (default: 30)")
    creds.add_argument("--overwrite", action="store_true", help="replace what DIR holds")
    creds.set_defaults(run="dmo.commands.credentials:run")


def rate(text: str) -> float:
    if text.lower() in ("max", "0"):
        return 0.0
    value = nonneg_float(text)
    if value == 0:
        raise argparse.ArgumentTypeError(f"expected a positive rate or max, got {text!r}")
    return value


def _add_recording_commands(sub) -> None:
    """record, info, replay and settle: the verbs of rosbag2 and the MCAP tools, on dmosim recordings."""
    from messages.recording import CHUNK_MESSAGES, FLUSH_INTERVAL_S  # noqa: PLC0415
    from messages.transport import add_bus_arguments  # noqa: PLC0415

    record = sub.add_parser("record", help="the recorder role: every message of one run into an MCAP file")
    record.add_argument("--out", required=True, metavar="PATH", help="the MCAP file to write")
    record.add_argument("--run-id", default="day", help="the run whose prefix is recorded (default: day)")
    record.add_argument("--overwrite", action="store_true", help="replace an existing file")
    record.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                        help="add to the recording's metadata record (repeatable)")
    record.add_argument("--attach", action="append", default=[], metavar="PATH",
                        help="store a file (case, fleet) in the recording (repeatable)")
    record.add_argument("--chunk-messages", type=positive_int, default=CHUNK_MESSAGES,
                        help=f"close a chunk after this many messages (default: {CHUNK_MESSAGES})")
    record.add_argument("--flush-interval", type=nonneg_float, default=FLUSH_INTERVAL_S, metavar="S",
                        help=f"close a chunk at least this often, seconds (default: {FLUSH_INTERVAL_S:g})")
    record.add_argument("--ready-file", metavar="PATH", help="write this file once the recorder listens")
    record.add_argument("--quiet", action="store_true")
    add_bus_arguments(record)
    record.set_defaults(run="dmo.commands.record:run")

    info = sub.add_parser("info", help="summary of a recording: run, market day, agents, channels, counts")
    info.add_argument("path", help="an MCAP recording")
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.set_defaults(run="dmo.commands.info:run")

    replay = sub.add_parser("replay", help="republish a recording over Zenoh under a new run prefix")
    replay.add_argument("path", help="an MCAP recording")
    replay.add_argument("--rate", type=rate, default=1.0, help="speed-up of the original spacing, or max (default: 1)")
    replay.add_argument("--topics", action="append", default=[], metavar="PATTERN",
                        help="only keys matching this pattern, relative to the run prefix, e.g. 'dmo/*' or "
                             "'agent/*/meter' (* one level, ** any; repeatable)")
    replay.add_argument("--start-offset", type=nonneg_float, default=0.0, metavar="S",
                        help="start this many seconds into the recording (default: 0)")
    replay.add_argument("--loop", action="store_true", help="play again from the start when done, until interrupted")
    replay.add_argument("--run-id", default=None, help="run prefix to publish under (default: a new run id)")
    replay.add_argument("--wait-for-subscriber", type=nonneg_float, default=5.0, metavar="S",
                        help="wait up to S seconds for someone to listen before the first message (default: 5)")
    replay.add_argument("--as-dmo", action="store_true",
                        help="play only the DMO's side, paced by a live agent's answers, and settle that agent")
    replay.add_argument("--agent", help="with --as-dmo: the recorded agent the live agent stands in for "
                                        "(default: the first awarded one)")
    replay.add_argument("--timeout", type=nonneg_float, default=600.0, metavar="S",
                        help="with --as-dmo: how long to wait for each answer of the live agent (default: 600)")
    replay.add_argument("--record", metavar="PATH", help="with --as-dmo: record the replayed day to this MCAP file")
    replay.add_argument("--overwrite", action="store_true", help="replace an existing file at --record PATH")
    replay.add_argument("--json", action="store_true", help="print one JSON object at the end")
    replay.add_argument("--quiet", action="store_true")
    add_bus_arguments(replay)
    replay.set_defaults(run="dmo.commands.replay:run")

    settle = sub.add_parser("settle", help="re-settle a recorded day and compare with its recorded statements")
    settle.add_argument("path", help="an MCAP recording")
    settle.add_argument("--penalty", type=nonneg_float, default=None, metavar="C",
                        help="re-settle under this penalty rate ($/MWh) and print the change per agent")
    settle.add_argument("--credit", type=nonneg_float, default=None, metavar="C",
                        help="re-settle under this under-import credit rate ($/MWh)")
    settle.add_argument("--json", action="store_true", help="print one JSON object")
    settle.set_defaults(run="dmo.commands.settle:run")


def _load(target: str):
    module, _, func = target.partition(":")
    return getattr(__import__(module, fromlist=[func]), func)


def main(argv: list[str] | None = None) -> int:
    try:
        argv = sys.argv[1:] if argv is None else argv
        args = build_parser(argv[0] if argv and not argv[0].startswith("-") else None).parse_args(argv)
        return _load(args.run)(args) or 0
    except (UsageError, CaseError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a runtime failure: one line, unless DMOSIM_DEBUG asks for the traceback
        if os.environ.get("DMOSIM_DEBUG"):
            raise
        detail = str(exc) if isinstance(exc, RuntimeError) else f"{type(exc).__name__}: {exc}"
        print(f"failed: {detail}", file=sys.stderr)
        return EXIT_FAILURE


def _native_stdout_to_stderr() -> None:
    """Keep stdout for what dmosim prints (``--json`` output is parsed by other programs): native libraries that
    write to file descriptor 1 behind Python's back, such as HiGHS 1.16, which prints its banner whenever a
    solver object is created and before any option can silence it, go to stderr instead. Forked workers and
    child processes inherit the same arrangement."""
    sys.stdout.flush()
    stdout = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = open(stdout, "w", buffering=1, encoding=sys.stdout.encoding, errors=sys.stdout.errors)


def console() -> int:
    """The ``dmosim`` executable: ``main`` with stdout reserved for dmosim's own output."""
    _native_stdout_to_stderr()
    return main()


if __name__ == "__main__":
    sys.exit(console())
