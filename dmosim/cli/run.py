"""``dmosim run [EXPERIMENT]``: market days as separate OS processes (the DMO, one per agent, the recorder) over
Zenoh on this machine, from an experiment file and flags (docs/experiments.md), into a run directory.

Every flag overrides the experiment file's setting of the same name; with neither, the experiment's default holds.
The run directory (``./runs/<run_id>/`` unless ``--out``) receives the resolved experiment, the recording, the
DMO's result, the recording as tables and a figure, and the roles' logs (dmosim/experiment/rundir.py).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import re
import sys
from pathlib import Path

from dmo.market.choice import Trust, UntrustedRule, choose
from dmo.operator.report import StoppedShort
from messages.keys import new_run_id
from microgrid_agent.agent.strategies import strategy_name
from scenarios.case import load_case, parse_toml
from scenarios.fleet import FleetError
from scenarios.network import NETWORKS

from ..arguments import integer
from ..console import Mark, Progress, UsageError, left_words, print_json, run_time_left, stop_on_terminate
from ..experiment.rundir import RunDir, RunDirError
from ..experiment.spec import (FLAGS, IN_PROCESS, Experiment, ExperimentError, load_experiment, parse_experiment,
                               settled_by, with_settings)
from ..launch.cluster import Cluster
from ..launch.faults import Fault, parse_fault
from .placement import add_cluster_flag, check_cluster, check_shared, connected
from ..launch.local import RoleFailed, run_locally
from ..launch.mesh import router_names
from ..launch.roles import fleet_written, resolved, strategy_of
from ..launch.viewing import Viewing
from ..results.order import natural
from ..results.report import RunReport
from ..results.verdict import one_line
from .checks import Checked, agent_list, check_inputs, strategy_source
from .flags import add_trust_flag, check_out, load_recording, recording_file, recording_path, untrusted
from .settings import add_setting_flags, experiment_with_flags

HELP = "market days as processes: the DMO and one process per agent over Zenoh, from an experiment file and flags"
FAULT_HELP = ("a fault to inject (repeatable; docs/faults.md): kill:AGENT:HOUR[:DAY] (SIGKILL the agent when the "
              "clock reaches HOUR of DAY, default 1; AGENT may be recorder: the run goes on and exits 1), "
              "restart:AGENT:HOUR[:DAY] (SIGKILL it, then start it again: it "
              "rejoins; AGENT may be dmo: it resumes the run from its journal), and on the messages "
              "whose key, relative to the run prefix, matches PATTERN (* one level, ** any, e.g. agent/*/meter): "
              "drop:PATTERN:P, duplicate:PATTERN:P, corrupt:PATTERN:P (each with probability P) and "
              "delay:PATTERN:SECONDS[:P]; seeded by --seed")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("experiment", nargs="?", metavar="EXPERIMENT",
                   help="an experiment file (TOML, docs/experiments.md); the flags below override it")
    p.add_argument("--from", dest="source", metavar="RECORDING",
                   help="run again the experiment that a recording, or a run directory, of dmosim run holds (flags override it)")
    setting = p.add_argument_group("the experiment (each overrides the file; default: the file's, else shown)")
    add_setting_flags(setting, FLAGS)
    setting.add_argument("--in-process", dest=FLAGS["agents.hosting"], action="store_const", const=IN_PROCESS,
                         help=f"the same as --hosting {IN_PROCESS}: the whole market in this process, no network")
    setting.add_argument("--fault", action="append", metavar="SPEC", help=FAULT_HELP)
    out = p.add_argument_group("output")
    out.add_argument("--out", metavar="DIR", help="the run directory (default: runs/<run_id>)")
    out.add_argument("--overwrite", action="store_true", help="use --out DIR even if it holds a run")
    record = out.add_mutually_exclusive_group()
    record.add_argument("--record", metavar="PATH", help="the recording (default: DIR/recording.mcap)")
    record.add_argument("--no-record", action="store_true", help="run without a recorder")
    out.add_argument("--json", action="store_true", help="print one JSON object (docs/experiments.md, \"The result\")")
    out.add_argument("--quiet", action="store_true", help="no progress bar or lines on stderr")
    out.add_argument("--view", action="store_true",
                     help="serve the run's live page on localhost and print its URL; the page stays up after the run "
                          "until Ctrl-C (docs/view.md; pip install 'dmosim[view]')")
    out.add_argument("--view-port", type=integer(0, 65535), default=0, metavar="PORT",
                     help="with --view: the page's port (default: 0, a free port)")
    out.add_argument("--view-url-file", metavar="PATH",
                     help="with --view: write the page's URL and a newline to this file once it serves")
    out.add_argument("--check", action="store_true",
                     help="check the inputs (experiment, cases, fleet, faults, paths, --out) and exit without running")
    add_trust_flag(p)
    place = p.add_argument_group("placement (docs/cluster.md)")
    add_cluster_flag(place, "the agents (the DMO, the recorder and this launcher stay here)")
    place.add_argument("--advertise", metavar="HOST",
                       help="with --cluster: the address of this machine that the workers reach the DMO at (default: "
                            "the one this machine reaches the scheduler from)")
    p.add_argument("--tls", action="store_true",
                   help="also connect the roles over mutual TLS with certificates made for this run (the per-run "
                        "passwords and access control are always on; docs/security.md)")


def experiment_of(args) -> Experiment:
    """The experiment the arguments describe: a file (or a recording's), then every flag given."""
    if args.experiment and args.source:
        raise UsageError("give an experiment file or --from RECORDING, not both")
    try:
        if args.experiment:
            base = load_experiment(args.experiment)
        elif args.source:
            base = experiment_in_recording(args.source)
        else:
            base = Experiment()
        experiment = experiment_with_flags(base, args)
        if args.fault is not None:
            experiment = with_settings(experiment, {"faults": list(args.fault)}, "flags")
    except ExperimentError as exc:
        raise UsageError(str(exc)) from None
    _load_rule(args, experiment.market.settlement)
    _trust_feeder(args, experiment.network.feeder)
    return experiment


def _load_rule(args, spec: str | None) -> None:
    """Load and try the run's settlement rule before anything starts: one the user named (``--settlement``, or the
    experiment file given) at once; one only the recording of ``--from`` names, if it is built in, or with
    ``--trust-rules`` (docs/settlement.md, "Rules named by recordings")."""
    if args.trust_rules and not args.source:
        raise UsageError("--trust-rules goes with --from RECORDING")
    if spec is None:
        return
    where = ("--settlement" if args.settlement is not None else
             f"{args.experiment}: market.settlement" if args.experiment else
             f"{args.source}: its experiment.toml: market.settlement")
    try:
        if args.settlement is not None or args.experiment:
            choose(spec)
        else:
            Trust(everything=args.trust_rules).choose(spec)
    except UntrustedRule as err:
        raise untrusted(f"{args.source}: its experiment.toml names the settlement rule {err.spec}", err.spec,
                        "--settlement") from None
    except ValueError as err:
        raise UsageError(f"{where}: {err}") from None


def _trust_feeder(args, feeder: str | None) -> None:
    """A feeder file that only the recording of ``--from`` names is read with ``--trust-rules`` only, as its code
    would be run: the user names a feeder with ``--feeder`` (docs/network.md, "A feeder in an experiment"). A
    built-in feeder is no file."""
    if args.source and args.feeder is None and feeder is not None and feeder not in NETWORKS and not args.trust_rules:
        raise untrusted(f"{args.source}: its experiment.toml names the feeder file {feeder}", feeder, "--feeder",
                        "feeder file", "docs/network.md, \"A feeder in an experiment\"", "read")


def _load_strategies(args, experiment: Experiment, fleet) -> None:
    """Make, and try on a trial call, each strategy the run's agents bid with, before anything starts: one the user
    named (``--strategy``, ``--fleet``, or the experiment file given) at once; one only the recording of ``--from``
    names, if it is built in, the same code as ``--strategy`` names, or with ``--trust-rules`` (docs/strategies.md,
    "Trust"). The agents load them again, each its own."""
    named = {strategy_name(args.strategy).code} - {None} if args.strategy else set()
    trust = Trust(everything=args.trust_rules, named=frozenset(named))
    checked = Checked()
    for member in fleet:
        spec = strategy_of(experiment, member)
        mine = not args.source or bool(args.fleet if member.strategy else args.strategy)
        if not mine and not trust.allows_code(strategy_name(spec).code):
            raise untrusted(f"{args.source}: its experiment names the strategy {spec} for {member.id}", spec,
                            "--strategy", "strategy", "docs/strategies.md")
        where = (strategy_source(experiment, member) if member.strategy else "--strategy" if args.strategy else
                 f"{args.experiment or args.source}: agents.strategy" if args.experiment or args.source else
                 "agents.strategy")
        checked.strategy(spec, member, where)


def experiment_in_recording(path: str) -> Experiment:
    """The resolved experiment a recording of ``dmosim run`` holds (its attachment experiment.toml, checked against
    its CRC by the reader), parsed as data: a settlement rule it names is a name, not loaded (``_load_rule``)."""
    rec = load_recording(path)
    for attachment in rec.attachments:
        if attachment.name == "experiment.toml":
            try:
                source = f"{path}: experiment.toml"
                return parse_experiment(parse_toml(attachment.data.decode(), source, ExperimentError), source)
            except UnicodeDecodeError as exc:
                raise UsageError(f"{path}: its experiment.toml cannot be read: {exc}") from None
            except ExperimentError as exc:
                raise UsageError(str(exc)) from None
    raise UsageError(f"{path}: holds no experiment.toml, the resolved experiment --from repeats: a recording made by "
                     "hand (dmosim record beside dmosim dmo and agent) has it only if attached (dmosim record --attach "
                     "experiment.toml, the experiment its roles ran); run that experiment file instead "
                     "(docs/experiments.md, \"Roles started by hand\")")


def run(args) -> int:
    experiment = experiment_of(args)
    try:
        experiment = resolved(experiment)  # on a feeder, places the agents: a fleet or bus that cannot be is here
        fleet = check_inputs(experiment)
        _load_strategies(args, experiment, fleet)
    except (ExperimentError, FleetError) as exc:
        raise UsageError(str(exc)) from None
    record_to = recording_path(args.record, args.overwrite) if args.record else None
    recorder_faults = [f for f in map(parse_fault, experiment.faults) if isinstance(f, Fault) and f.agent == "recorder"]
    if args.no_record and recorder_faults:
        raise UsageError(f"--fault {recorder_faults[0]}: there is no recorder to kill with --no-record")
    _check_placement(args, experiment, fleet)
    _check_view(args, experiment)
    if args.check:
        check_out(args)
        rule = settled_by(experiment.market, load_case(experiment.market.case).grid.penalty)
        drawn = (f" drawn diverse from seed {experiment.seed} (the run writes them to its directory's fleet.toml)"
                 if experiment.agents.generate is not None else "")
        print(f"dmosim run: inputs are valid: {experiment.days} day(s) from {experiment.market_day}, {len(fleet)} "
              f"agents ({agent_list(fleet)}){drawn}, case {experiment.market.case}, settled by {rule}, bidding with "
              f"{', '.join(sorted({strategy_of(experiment, m) for m in fleet}))}, "
              + (f"on feeder {experiment.network.feeder} at buses {', '.join(experiment.network.buses)}, "
                 if experiment.network.feeder else "")
              + (f"against the ISO's curve ({len(experiment.market.import_curve)} import and "
                 f"{len(experiment.market.export_curve)} export blocks), "
                 if experiment.market.import_curve or experiment.market.export_curve else "")
              + f"{len(experiment.faults)} fault(s)")
        return 0
    # The cluster is reached before the run directory is made: one that does not answer leaves nothing behind.
    with connected(args, args.advertise) if args.cluster else contextlib.nullcontext() as cluster:
        return _launch(args, experiment, record_to, cluster)


def _launch(args, experiment: Experiment, record_to: Path | None, cluster: Cluster | None) -> int:
    """The run itself, into its new run directory; its exit code."""
    run_id = new_run_id()
    try:
        rundir = RunDir.make(args.out, run_id, args.overwrite)
    except RunDirError as exc:
        raise UsageError(str(exc)) from None
    experiment = fleet_written(experiment, rundir.fleet)  # a generated fleet: every role reads the run's own file
    record = None if args.no_record else (record_to or rundir.recording)
    bar = None if args.quiet else Progress("hours")
    say, tick = (bar.say, _estimating(bar, experiment.days)) if bar else (lambda text: None, lambda *_: None)
    stop_on_terminate()  # a terminated run stops its roles like Ctrl-C does
    # the page's process outlives the run (its end stays on the page until Ctrl-C), so it is stopped last
    with Viewing(args.view_port, args.view_url_file, _printed) if args.view else contextlib.nullcontext() as view:
        try:
            if cluster:
                check_shared(cluster, rundir.root)
            repeat_of = recording_file(args.source) if args.source else None  # a run directory's recording.mcap
            result = run_locally(experiment, run_id, rundir, record=record, tls=args.tls, repeat_of=repeat_of,
                                 say=say, tick=tick, cluster=cluster, view=view)
        except RoleFailed as exc:
            if bar:
                bar.close()
            for name in exc.names:
                _tail(rundir.logs / f"{name}.log")
            raise
        finally:
            if bar:
                bar.close()
        if args.json:
            print_json(result.model_dump(mode="json"))
        else:
            print(summary_table(result))
        ok = result.verdict.ok
        if not ok:  # the run is over and its files are written, but its results are not to be trusted
            print(f"failed: {one_line(result.verdict.problems)}", file=sys.stderr)
        if view is not None:
            sys.stdout.flush()
            view.linger()
    return 0 if ok else 1  # a run whose results are not to be trusted: the same exit as any run that went wrong


def _estimating(bar: Progress, days: int):
    """``bar.update`` with the time left from the work of the run's phases so far (``run_time_left``): each clock
    message (its ``mark``) is noted when seen."""
    marks: list[Mark] = []

    def tick(done: int, total: int, text: str, mark: tuple | None = None) -> None:
        if mark is not None:
            marks.append(Mark(bar.clock(), *mark))
        bar.update(done, total, text, left_words(run_time_left(marks, days, bar.clock())))
    return tick


def _printed(text: str) -> None:
    """A line about the run's page on stderr, even with --quiet: the URL is what --view asks for."""
    print(text, file=sys.stderr, flush=True)


def _check_view(args, experiment: Experiment) -> None:
    """``--view`` and its flags, before anything starts: the page watches roles over Zenoh (not in-process), on a
    port that is free, with the extra 'view' installed."""
    if not args.view:
        given = [f for f, v in (("--view-port", args.view_port), ("--view-url-file", args.view_url_file)) if v]
        if given:
            raise UsageError(f"{given[0]} goes with --view")
        return
    if experiment.agents.hosting == IN_PROCESS:
        raise UsageError(f"--view: hosting \"{IN_PROCESS}\" runs the market with no network, which the page watches; "
                         "run the roles as processes")
    missing = [name for name in ("starlette", "uvicorn") if importlib.util.find_spec(name) is None]
    if missing:
        raise UsageError(f"--view needs the extra 'view' ({missing[0]} is missing): pip install 'dmosim[view]'")
    if args.view_port:
        from ..view.server import BindError, bind  # noqa: PLC0415

        try:
            bind("127.0.0.1", args.view_port).close()
        except BindError as exc:
            raise UsageError(f"--view-port: {exc}") from None


def _check_placement(args, experiment: Experiment, fleet) -> None:
    """``--cluster`` and ``--advertise`` as given, before anything starts: a process fault on an agent needs the
    agent's process here (docs/cluster.md, "What is supported")."""
    if args.advertise is not None and args.cluster is None:
        raise UsageError("--advertise goes with --cluster")
    if args.advertise is not None and not re.fullmatch(r"[A-Za-z0-9.:_-]{1,253}", args.advertise):
        raise UsageError(f"--advertise {args.advertise!r}: expected a host name or an IP address")
    check_cluster(args)
    if experiment.agents.hosting == IN_PROCESS and (args.cluster or args.tls):
        raise UsageError(f"--{'cluster' if args.cluster else 'tls'}: hosting \"{IN_PROCESS}\" runs every role in this "
                         "process, with no network")
    agents = {m.id for m in fleet}
    remote = [f for f in map(parse_fault, experiment.faults) if isinstance(f, Fault) and f.agent in agents]
    if args.cluster and remote:
        raise UsageError(f"--fault {remote[0]}: with --cluster the agents run on the cluster's workers, where this "
                         "launcher cannot signal them; kill and restart faults may name the dmo or the recorder")
    if args.cluster and (experiment.agents.per_process or 1) > 1:
        raise UsageError(f"agents.per_process = {experiment.agents.per_process}: with --cluster each worker forks its "
                         "agents one to a process; give 1")
    if args.cluster and experiment.agents.routers:
        raise UsageError(f"agents.routers = {experiment.agents.routers}: with --cluster the agents connect to the DMO "
                         "from the workers; give 0, or run routers on the hosts yourself (docs/hosts.md)")
    taken = sorted(agents & set(router_names(experiment.agents.routers)))
    if taken:
        raise UsageError(f"agents.routers = {experiment.agents.routers}: {taken[0]} is the name of a router of the run "
                         "and of an agent; rename the agent")


def _tail(path: Path, lines: int = 15) -> None:
    if path.exists():
        for line in path.read_text(errors="replace").splitlines()[-lines:]:
            print(f"    {line}", file=sys.stderr)


def _stopped(schedule: StoppedShort) -> str:
    """One schedule stopped short, as the summary names it: agent, market day (of a run of several), status and
    certified gap."""
    day = f" {schedule.market_day}" if schedule.market_day is not None else ""
    gap = "" if schedule.mip_gap is None else f" at gap {100 * schedule.mip_gap:.2f}%"
    return f"{schedule.agent}{day} {schedule.status}{gap}"


def summary_table(result: RunReport) -> str:
    """Per agent: award energy, realised import, deviation energy, energy charge, penalty and total."""
    head = f"{'agent':<8}{'award MWh':>11}{'import MWh':>12}{'dev. MWh':>10}{'energy $':>12}{'penalty $':>11}{'total $':>12}"
    days = result.days
    when = (f"market day {days[0].market_day}" if len(days) == 1 else
            f"{len(days)} market days, {days[0].market_day} to {days[-1].market_day} (totals)")
    rows = [f"{when}, run {result.run_id}", head, "-" * len(head)]
    for agent, s in sorted(result.settlement.items(), key=lambda item: natural(item[0])):
        rows.append(f"{agent:<8}{s.award_mwh:>11.2f}{s.import_mwh:>12.2f}{s.deviation_mwh:>10.3f}"
                    f"{s.energy_charge:>12,.2f}{s.deviation_penalty:>11,.2f}{s.total:>12,.2f}")
    islanded = "; ".join(f"{d.market_day}: {', '.join(map(str, d.islanded_hours)) or 'none'}" for d in days)
    rows.append(f"settled by: {result.settlement_rule}")
    rows.append(f"rejected messages: {result.rejected_messages}; islanded hours: {islanded}")
    short = result.schedules_stopped_short
    if short:
        rows.append(f"schedules stopped short of their gap: {len(short)} ({', '.join(map(_stopped, short))})")
    recorded = result.recorded
    if result.recording:
        rows.append(f"recording: {result.recording}" + (
            f" ({recorded.messages} messages on {recorded.channels} channels, {recorded.bytes:,} bytes"
            f"{'' if recorded.complete else ', INCOMPLETE'})" if recorded and recorded.messages is not None else
            f" ({(recorded and recorded.error) or 'unreadable'})"))
        if recorded and recorded.recorder:
            rows.append(f"recorder: {recorded.recorder}")
        if recorded and recorded.tables_from == "journal":
            rows.append("tables and figure: from the DMO's journal, which holds every message it sent or received")
    else:
        rows.append("recording: none (--no-record)")
    rows.append(f"run directory: {result.run_dir}" + (" (experiment.toml, result.json, tables/, run.png, logs/)"
                                                      if result.figure else ""))
    for incident in result.incidents:
        where = incident.phase + (f" hour {incident.hour}" if incident.hour else "")
        where = f"{incident.market_day} {where}" if incident.market_day is not None else where
        rows.append(f"incident [{where}] {incident.agent or '-'}: {incident.reason}")
    problems = result.verdict.problems
    rows.append("verdict: ok" if not problems else f"verdict: NOT OK, {len(problems)} problem(s):")
    rows += [f"  {line}" for line in problems]
    return "\n".join(rows)
