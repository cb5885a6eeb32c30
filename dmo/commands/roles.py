"""``dmosim dmo``, ``dmosim agent`` and ``dmosim router``: one role each, for runs spread over several hosts."""

from __future__ import annotations

import datetime as dt
import json
import logging
import sys
import threading
from pathlib import Path

from messages.security import auth_settings
from messages.transport import Bus, BusConfig, bus_config_from_args
from scenarios.case import load_case
from scenarios.fleet import derive_case

from ..console import UsageError
from ..day import DayConfig, MarketDay, draw_islanding

log = logging.getLogger("dmosim")


def setup_logging(role: str, quiet: bool = False) -> None:
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {role} %(levelname)s %(message)s", datefmt="%H:%M:%S")


def _bus_config(args, default_mode: str, name: str | None = None, run_id: str | None = None) -> BusConfig:
    """The bus settings of the flags; ``name`` is who a client logs in as by default, and a router with ``run_id``
    checks that its --auth-dir was made for that run (messages/security.py)."""
    try:
        config = bus_config_from_args(args)
        mode = config.mode or default_mode
        auth = auth_settings(args, name, router=mode == "router", run_id=run_id,
                             endpoints=config.listen if mode == "router" else config.connect)
        if mode == "router" and not auth:
            log.warning("no --auth-dir: anyone who reaches %s may join and publish anything (trusted networks "
                        "only; docs/security.md)", ", ".join(config.listen) or "this router")
        return BusConfig(mode=mode, connect=config.connect, listen=config.listen, lease_s=config.lease_s,
                         connect_timeout_s=config.connect_timeout_s,
                         config_file=config.config_file, overrides=config.overrides + auth)
    except ValueError as exc:  # AuthError is one
        raise UsageError(str(exc)) from None


def day_config(args) -> DayConfig:
    case = load_case(args.case)
    return DayConfig(
        market_day=args.market_day or today(), agents=args.agents, iso_price=tuple(case.grid.iso_price),
        import_limit=args.import_limit if args.import_limit is not None else 8.0 * args.agents,
        export_limit=args.export_limit if args.export_limit is not None else 5.0 * args.agents,
        penalty=case.grid.penalty if args.penalty is None else args.penalty, credit=args.credit,
        subperiods=args.subperiods, islanded_hours=draw_islanding(args.island_hours, args.seed),
        fixed_awards=tuple(case.grid.p_sch) if args.market == "fixed" else None,
        registration_s=args.registration_timeout, bids_s=args.bid_timeout, schedule_s=args.schedule_timeout,
        hour_s=args.hour_timeout, journal=getattr(args, "journal", None))


def run_dmo(args) -> int:
    setup_logging("dmo", args.quiet)
    config = day_config(args)
    progress = lambda phase, hour: log.info("phase %s%s", phase, f" hour {hour}/24" if hour else "")  # noqa: E731
    with Bus(args.run_id, "dmo", _bus_config(args, "router", "dmo", args.run_id)) as bus:
        bus.faults = message_faults(args, bus)
        before_start = (lambda: await_recorder(bus, args.await_recorder)) if args.await_recorder else None
        result = MarketDay(bus, config, progress).run(before_start)
        bus_stats = bus.stats() | ({"faults_injected": bus.faults.summary()} if bus.faults else {})
    out = result_object(args.run_id, config, result, bus_stats)
    text = json.dumps(out, indent=2)
    if args.result:
        Path(args.result).write_text(text + "\n")
    else:
        print(text)
    return 0


def await_recorder(bus: Bus, timeout_s: float) -> None:
    """Block until the run's recorder is present (its token is declared after its subscription, so it listens)."""
    present = threading.Event()
    with bus.watch_presence(lambda name: name == "recorder" and present.set(), lambda name: None):
        if not present.wait(timeout_s):
            raise RuntimeError(f"no recorder joined run {bus.keys.run_id} within {timeout_s:g} s")
    log.info("recorder present")


def result_object(run_id: str, config: DayConfig, result, bus_stats: dict) -> dict:
    """The ``dmosim run --json`` object of SPEC section 4, from the DMO's view of the day."""
    s = result.state
    return {
        "run_id": run_id, "market_day": config.market_day, "agents": sorted(s.registered),
        "islanded_hours": list(config.islanded_hours),
        "clearing_prices": list(result.clearing.price), "congestion": list(result.clearing.congested),
        "awards": {a: list(v) for a, v in result.clearing.awards.items()},
        "settlement": {a: {"energy_charge": float(st.energy_charge), "deviation_penalty": float(st.deviation_penalty),
                           "credit": float(st.credit), "total": float(st.total),
                           "award_mwh": sum(line.award_mwh for line in st.lines),
                           "import_mwh": sum(line.import_mwh for line in st.lines),
                           "deviation_mwh": sum(line.deviation_mwh for line in st.lines),
                           "missing_subperiods": st.missing_subperiods}
                       for a, st in result.statements.items()},
        "day_summary": result.summary.as_dict(),
        "expected_cost": {a: m.expected_cost for a, m in s.schedules.items()},
        "rejected_messages": s.rejected, "rejected_by_code": dict(s.rejected_by_code),
        "accepted_messages": dict(s.accepted), "transport": bus_stats,
        "incidents": [i.model_dump() for i in s.incidents],
        "phase_s": result.phase_s,
    }


def run_agent(args) -> int:
    # imported here: the agent's solver stack takes seconds to import, and the other roles (DMO, recorder,
    # replay) share this module
    from microgrid_agent.agent import AgentConfig, MicrogridAgent  # noqa: PLC0415

    setup_logging(args.id, args.quiet)
    case = derive_case(load_case(args.case), args.scale, args.shift_hours, args.case if args.scale == 1 else f"{args.case}x{args.scale:g}")
    config = AgentConfig(scenarios=args.scenarios, island_hours=args.island_hours, gap=args.gap,
                         time_limit=args.time_limit, seed=args.seed, idle_s=args.idle_timeout, method=args.method,
                         workers=args.workers)
    with Bus(args.run_id, args.id, _bus_config(args, "client", args.id)) as bus:
        bus.faults = message_faults(args, bus)
        MicrogridAgent(bus, case, config, args.market_day or today()).run()
    return 0


def message_faults(args, bus: Bus):
    """The FaultInjector of the ``--fault`` message faults (messages/faults.py) for this process's bus, or None."""
    from messages.faults import FaultSpecError, injector  # noqa: PLC0415

    try:
        faults = injector(getattr(args, "fault", []), bus.keys.prefix, getattr(args, "fault_seed", 0), bus.name)
    except FaultSpecError as exc:
        raise UsageError(f"--fault: {exc}") from None
    if faults is not None:
        log.warning("injecting message faults: %s", ", ".join(map(str, faults.faults)))
    return faults


def run_router(args) -> int:
    """A standalone Zenoh router; the DMO and agents then connect to it as clients."""
    setup_logging("router", args.quiet)
    import zenoh  # noqa: PLC0415

    config = _bus_config(args, "router")
    stop = threading.Event()
    with zenoh.open(config.to_zenoh()):
        log.info("router listening on %s", ", ".join(config.listen) or "zenoh's default endpoints")
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    return 0


def today() -> str:
    return dt.date.today().isoformat()
