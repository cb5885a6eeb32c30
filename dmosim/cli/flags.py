"""What several verbs share on the command line: the flag groups of the roles (Zenoh endpoints, credentials,
message faults), the logging of a role, and where a recording may go; the value types are in dmosim/arguments.py.

A verb's own flags sit beside its body, in its module; only what two verbs or more take is here.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from messages.keys import Keys, check_run_id, new_run_id
from messages.recording import Recording, RecordingError, read_recording
from messages.transport import MODES, BusConfig
from messages.transport.access import READERS, USERS_FILE, AuthError, auth_settings
from messages.transport.credentials import check_private, create_auth_dir, private_directory
from messages.transport.faults import FaultInjector, FaultSpecError, injector, parse_message_fault
from scenarios.days import MAX_SEED
from scenarios.fleet import FleetError, load_fleet, make_fleet

from ..arguments import seed
from ..console import LOG_DATEFMT, LOG_FORMAT, UsageError
from ..experiment.rundir import RunDir, RunDirError, check_directory
from ..experiment.spec import MAX_FAULTS, Experiment
from ..launch.roles import message_faults as experiment_message_faults

log = logging.getLogger("dmosim")
DEFAULT_CREDENTIALS = "dmosim-credentials"  # where a router that was given none makes its run's credentials
DEFAULT_AGENTS = 3  # the agents credentials are made for, given neither --agents nor --fleet


# --- flag groups --------------------------------------------------------------------------------------------------

def add_fault_flags(p: argparse.ArgumentParser) -> None:
    """Message faults on what one role publishes: ``dmo``, ``agent`` (``run`` takes process faults too)."""
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="message fault on what this process publishes, beside those of the experiment: "
                        "drop|duplicate|corrupt:PATTERN:P or delay:PATTERN:SECONDS[:P] (repeatable; docs/faults.md)")
    p.add_argument("--fault-seed", type=seed, help=f"seed of the fault draws, 0..{MAX_SEED} (default: the "
                                                   "experiment's seed)")


def add_bus_flags(parser: argparse.ArgumentParser, default_mode: str) -> None:
    """The Zenoh and authentication flags every networked role takes; ``default_mode`` says, for the help, the mode
    the verb takes without ``--mode``. Never a password on the command line: it would show in ``ps``."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=MODES, help=f"zenoh session mode (default: {default_mode})")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file; the flags above override it")
    group.add_argument("--lease", type=float, metavar="SECONDS",
                       help="liveliness lease: how soon a frozen process is declared gone (zenoh default 10)")
    group.add_argument("--connect-timeout", type=float, default=60.0, metavar="SECONDS",
                       help="how long a client keeps trying the --connect endpoints before giving up (default "
                            "60), so a process may start before the one it connects to; a router keeps trying "
                            "for as long as it runs")
    auth = parser.add_argument_group("authentication (docs/security.md)")
    auth.add_argument("--auth-dir", metavar="DIR",
                      help="credentials made by `dmosim credentials` (or `dmosim run`): the router uses DIR, a "
                           "client its bundle DIR/<its name>; without it the process joins, or serves, an open network")
    auth.add_argument("--user", metavar="NAME", help="log in as NAME (default: this process's name); a router that "
                                                    "--connect's to other routers logs in to them as NAME, with its "
                                                    "bundle DIR/NAME/ (docs/hosts.md)")
    auth.add_argument("--password-file", metavar="FILE", help="file holding the password (instead of --auth-dir)")
    auth.add_argument("--insecure", action="store_true",
                      help="serve or join an open network: no credentials, no access control (trusted networks "
                           "only). Without it a DMO or router makes the run's credentials itself")


def check_bus_flags(args, default_mode: str) -> None:
    """The bus flags' own values (mode, endpoints, lease, connect timeout), or the one-line UsageError, before a
    role makes or reads credentials."""
    try:
        BusConfig(mode=args.mode or default_mode, connect=tuple(args.connect), listen=tuple(args.listen),
                  lease_s=args.lease, connect_timeout_s=args.connect_timeout, config_file=args.zenoh_config)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def bus_config(args, default_mode: str, name: str | None = None, run_id: str | None = None) -> BusConfig:
    """The bus settings of the flags of ``add_bus_flags``; ``name`` is who a client logs in as by default, a
    router with ``run_id`` checks that its --auth-dir was made for that run (messages/transport/access.py), and a
    router that ``--connect``s to other routers logs in to them with its bundle (docs/hosts.md)."""
    try:
        mode = args.mode or default_mode
        listen, connect = tuple(args.listen), tuple(args.connect)
        if args.auth_dir:
            check_private(args.auth_dir)
        if args.password_file:
            check_private(args.password_file, secret=True)
        auth = auth_settings(args.auth_dir, args.user, args.password_file, name, router=mode == "router",
                             run_id=run_id, endpoints=listen + connect if mode == "router" else connect,
                             connects=bool(connect))
        if mode == "router" and not auth:
            log.warning("%s: anyone who reaches %s may join and publish anything (trusted networks only; "
                        "docs/security.md)", "--insecure" if args.insecure else "no --auth-dir",
                        ", ".join(listen) or "this router")
        return BusConfig(mode=mode, connect=connect, listen=listen, lease_s=args.lease,
                         connect_timeout_s=args.connect_timeout, config_file=args.zenoh_config, overrides=auth)
    except ValueError as exc:  # AuthError is one
        raise UsageError(str(exc)) from None


def agent_ids(fleet: str | None, agents: int) -> list[str]:
    """The agents of a run: those a fleet file names, else mg1..mgN."""
    try:
        return [m.id for m in (load_fleet(fleet) if fleet else make_fleet(agents))]
    except FleetError as exc:
        raise UsageError(str(exc)) from None


def run_id_of(args) -> str:
    """``--run-id``, checked, or else a new one (``messages.keys.new_run_id``: nobody can know it in advance), which
    ``announce_run_id`` then prints so that the other processes can be started against it."""
    if args.run_id is None:
        args.run_id, args.run_id_made = new_run_id(), True
    try:
        return check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(f"--run-id: {exc}") from None


def announce_run_id(args) -> None:
    """Say the run id ``run_id_of`` made, once everything else is checked."""
    if getattr(args, "run_id_made", False):
        print(f"dmosim: run {args.run_id} (start the other processes with --run-id {args.run_id})", file=sys.stderr,
              flush=True)


def credentials_for(args, run_id: str, agents: list[str], *, dmo_client: bool, scratch: Path | None = None) -> None:
    """Secure by default: a router that hosts a run (the DMO, ``dmosim router``, ``replay --as-dmo``) given no
    ``--auth-dir``, or one that does not exist yet, makes the run's credentials there itself (by default
    ``./dmosim-credentials/<run_id>/``; ``scratch/<run_id>/`` where the caller gives a private directory it removes
    when it ends) and says where every process's bundle is; ``args.auth_dir`` then names them. Credentials that are there already are used only if nobody else could have made or changed them
    (``check_private``). ``--insecure`` serves an open network instead. A client logs in with the bundle it is
    given, and so does a router that connects to other routers (a mesh, docs/hosts.md): it joins their run, whose
    credentials it must be given."""
    if args.insecure:
        if args.auth_dir:
            raise UsageError("--insecure and --auth-dir exclude each other: choose an open network or credentials")
        return
    if (args.mode or "router") != "router" or args.password_file or args.user:
        return
    if args.connect:
        if not args.auth_dir:
            raise UsageError("--connect: a router that connects to other routers joins their run; give it the run's "
                             "credentials, --auth-dir DIR --user NAME (docs/hosts.md), or --insecure")
        return
    where = Path(args.auth_dir) if args.auth_dir else (scratch or Path(DEFAULT_CREDENTIALS)) / run_id
    try:
        if not args.auth_dir:
            private_directory(where.parent)
        if (where / USERS_FILE).is_file():
            check_private(where)
            args.auth_dir = str(where)
            return
        create_auth_dir(where, run_id, agents, dmo_client=dmo_client)
    except AuthError as exc:
        raise UsageError(str(exc)) from None
    except (ValueError, OSError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise UsageError(f"cannot make the run's credentials in {where}: {why}") from None
    args.auth_dir = str(where)
    endpoint = (tuple(args.listen) or ("ENDPOINT",))[0]
    print(f"dmosim: made the credentials of run {run_id} in {where}: each process logs in with its bundle "
          f"{where}/<name>/ ({', '.join([*(['dmo'] if dmo_client else []), *READERS, *agents])}), e.g. dmosim "
          f"agent --id {agents[0]} --run-id {run_id} --connect {endpoint} --auth-dir {where}; copy to each host only "
          "its own bundle (docs/security.md)" + ("; they are removed when this process ends" if scratch and
                                                 where.parent == scratch else "")
          + ". --insecure serves an open network instead", file=sys.stderr)


def check_out(args) -> None:
    """``--check`` fails where the run or sweep would: ``--out DIR`` naming a directory that is not empty, without
    ``--overwrite``."""
    if args.out is not None:
        try:
            check_directory(Path(args.out), args.overwrite)
        except RunDirError as exc:
            raise UsageError(str(exc)) from None


def setup_logging(role: str, quiet: bool = False) -> None:
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, stream=sys.stderr,
                        format=LOG_FORMAT.format(role=role), datefmt=LOG_DATEFMT)


def recording_path(path: str, overwrite: bool) -> Path:
    """Where a recording may go: an existing directory, and no file there unless ``overwrite``."""
    out = Path(path)
    if out.is_dir():
        raise UsageError(f"{path} is a directory; give a file name, e.g. {out / 'day.mcap'}")
    if not out.parent.is_dir():
        raise UsageError(f"cannot write {path}: directory {out.parent} does not exist")
    if out.exists() and not overwrite:
        raise UsageError(f"{path} exists; remove it, choose another name or pass --overwrite")
    return out


RECORDING_HELP = "a recording (MCAP file) or a run directory (its recording.mcap)"  # what load_recording reads


def recording_file(path: str) -> str:
    """The recording PATH names: the file itself, or a run directory's recording.mcap."""
    if Path(path).is_dir() and RunDir(Path(path)).recording.is_file():
        return str(RunDir(Path(path)).recording)
    return path


def load_recording(path: str) -> Recording:
    """A recording (a file, or a run directory's), or the one-line UsageError (exit 2) of a file that is not one."""
    try:
        return read_recording(recording_file(path))
    except RecordingError as exc:
        raise UsageError(str(exc)) from None


def recorded_day_flag(rec: Recording, day: str | None) -> str | None:
    """``--day``: a market day the recording is of, else the one-line UsageError saying which days it is of."""
    from dmo.replay.resettle import recording_days  # noqa: PLC0415  (only for verbs that read recordings)

    days = recording_days(rec)
    if day is not None and day not in days:
        raise UsageError(f"--day {day}: {rec.path} is of {', '.join(days) or 'no market day'}")
    return day


def check_fault_flags(args) -> None:
    """``--fault``: at most MAX_FAULTS, each a message fault, or the one-line UsageError, before anything starts."""
    if len(args.fault) > MAX_FAULTS:
        raise UsageError(f"--fault: {len(args.fault)} faults; a process takes at most {MAX_FAULTS}")
    for spec in args.fault:
        try:
            parse_message_fault(spec)
        except FaultSpecError as exc:
            raise UsageError(f"--fault: {exc}") from None


def message_faults(args, run_id: str, name: str, experiment: Experiment) -> FaultInjector | None:
    """The FaultInjector (messages/transport/faults.py) of the experiment's message faults and the ``--fault`` ones
    for the bus of process ``name`` in run ``run_id``, drawn from ``--fault-seed`` (else the experiment's seed);
    None without faults."""
    specs = [str(f) for f in experiment_message_faults(experiment)] + args.fault
    seed = experiment.seed if args.fault_seed is None else args.fault_seed
    try:
        faults = injector(specs, Keys(run_id).prefix, seed, name)
    except FaultSpecError as exc:
        raise UsageError(f"--fault: {exc}") from None
    if faults is not None:
        log.warning("injecting message faults: %s", ", ".join(map(str, faults.faults)))
    return faults


SETTLEMENT_HELP = ("the settlement rule, NAME[:key=value,...] (paper, symmetric, deadband, price-linked) or "
                   "path/to/rules.py:function[:key=value,...] (docs/settlement.md; default: paper at --penalty and "
                   "--credit)")


STRATEGY_HELP = ("the agent's bidding strategy, NAME[:key=value,...] (price-response, table1, naive) or "
                 "path/to/strategy.py:Class[:key=value,...] (docs/strategies.md; default: price-response)")


TRUST_FLAG = "--trust-rules"


def add_trust_flag(p: argparse.ArgumentParser) -> None:
    """The one flag that lets a file's own code run, its settlement rules (``settle``, ``replay --as-dmo``, ``run
    --from``) and its agents' bidding strategies (``run --from``), and a feeder file it names be read (``run
    --from``)."""
    p.add_argument(TRUST_FLAG, dest="trust_rules", action="store_true",
                   help="load and run a settlement rule (path/to/rules.py:function or module:function) or bidding "
                        "strategy (path/to/strategy.py:Class) of its own that the recording names, and read a feeder "
                        "file it names; without it only a built-in, or one you name yourself, is used "
                        "(docs/settlement.md, \"Rules named by recordings\"; docs/strategies.md, \"Trust\"; "
                        "docs/network.md, \"A feeder in an experiment\")")


def untrusted(subject: str, spec: str, naming: str, what: str = "rule", doc: str = "docs/settlement.md",
              use: str = "run") -> UsageError:
    """The one line of a file that names code (or a file) of its own that the user did not: ``subject`` says where
    the file names ``spec``, ``what`` it is (``rule``, ``strategy``, ``feeder file``), ``use`` what dmosim would do
    with it (``run``, ``read``), ``doc`` where trust is explained; ``naming`` is the flag by which the user names it
    (``--rule``, ``--settlement``, ``--strategy``, ``--feeder``), or empty."""
    how = f"name it yourself ({naming} {spec}) or pass {TRUST_FLAG}" if naming else f"pass {TRUST_FLAG}"
    return UsageError(f"{subject}, a {what} of the recording's own, which dmosim does not {use} unless you {how} "
                      f"({doc})")
