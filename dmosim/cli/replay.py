"""``dmosim replay PATH``: republish a recorded day over Zenoh, or, with ``--as-dmo``, play the DMO's side of it to
a live agent process and settle that agent by the recorded rules (the DMO's machine running the recorded day,
replay/recorded.py; a rule of the recording's own
only with ``--trust-rules``).

Plain replay publishes every selected message at its recorded spacing scaled by ``--rate``, under a new run
prefix (``--run-id``, default a new id), so it never mixes with a live run. With ``--as-dmo --record PATH`` the
replayed day, the agent's messages included, is recorded.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import sys
import tempfile
import threading
from pathlib import Path

from dmo.market.choice import Trust, UntrustedRule
from dmo.replay.resettle import ResettleError, recorded_day, recorded_rule
from messages import DMO, check_agent_id, check_run_id, new_run_id
from messages.recording import Player, Recorder, Recording, RecordingWriter, select
from messages.transport import Bus

from ..arguments import market_day, nonneg_float
from ..console import UsageError, print_json, progress, stop_on_terminate
from .flags import (RECORDING_HELP, TRUST_FLAG, add_bus_flags, add_trust_flag, bus_config, credentials_for,
                    load_recording, recorded_day_flag, recording_path, setup_logging, untrusted)

HELP = "republish a recording (or a run directory's) over Zenoh under a new run prefix"


def rate(text: str) -> float:
    if text.lower() in ("max", "0"):
        return 0.0
    value = nonneg_float(text)
    if value == 0:
        raise argparse.ArgumentTypeError(f"expected a positive rate or max, got {text!r}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help=RECORDING_HELP)
    p.add_argument("--rate", type=rate, default=1.0, help="speed-up of the original spacing, or max (default: 1)")
    p.add_argument("--topics", action="append", default=[], metavar="PATTERN",
                   help="only keys matching this pattern, relative to the run prefix, e.g. 'dmo/*' or "
                        "'agent/*/meter' (* one level, ** any; repeatable)")
    p.add_argument("--start-offset", type=nonneg_float, default=0.0, metavar="S",
                   help="start this many seconds into the recording (default: 0)")
    p.add_argument("--loop", action="store_true", help="play again from the start when done, until interrupted")
    p.add_argument("--run-id", default=None, help="run prefix to publish under (default: a new run id)")
    p.add_argument("--wait-for-subscriber", type=nonneg_float, default=5.0, metavar="S",
                   help="wait up to S seconds for someone to listen before the first message (default: 5)")
    p.add_argument("--as-dmo", action="store_true",
                   help="play only the DMO's side, paced by a live agent's answers, and settle that agent")
    p.add_argument("--agent", help="with --as-dmo: the recorded agent the live agent stands in for "
                                   "(default: the first awarded one)")
    p.add_argument("--day", type=market_day, metavar="YYYY-MM-DD",
                   help="only this market day of a recording of several (with --as-dmo: played as a run of one "
                        "day; default: its first)")
    p.add_argument("--timeout", type=nonneg_float, default=600.0, metavar="S",
                   help="with --as-dmo: how long to wait for each answer of the live agent (default: 600)")
    p.add_argument("--record", metavar="PATH", help="with --as-dmo: record the replayed day to this MCAP file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file at --record PATH")
    p.add_argument("--json", action="store_true", help="print one JSON object at the end")
    p.add_argument("--quiet", action="store_true", help="log warnings only, no progress lines")
    add_trust_flag(p)
    add_bus_flags(p, "peer; router with --as-dmo")


def run(args) -> int:
    setup_logging("replay", args.quiet)
    run_id = args.run_id or new_run_id()
    try:
        check_run_id(run_id)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.as_dmo and (args.agent or args.record or args.trust_rules):
        raise UsageError(f"--agent, --record and {TRUST_FLAG} go with --as-dmo")
    rec = load_recording(args.path)
    recorded_day_flag(rec, args.day)
    if args.as_dmo:
        stop_on_terminate()  # SIGTERM as Ctrl-C: the recording is closed on the way out
        return _as_dmo(args, rec, run_id)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())

    messages = select(rec, args.topics, args.start_offset, args.day)
    if not messages:
        raise UsageError(f"{args.path}: nothing to replay" + (f" on keys matching {', '.join(args.topics)}"
                                                              if args.topics else "")
                         + (f" after {args.start_offset:g} s" if args.start_offset else ""))
    if rec.cut_note:
        print(f"warning: {args.path}: {rec.cut_note}; replaying what was recorded before the cut", file=sys.stderr)
    with Bus(run_id, "replay", bus_config(args, "peer"), announce=False) as bus, Player(bus, messages) as player:
        rate = "as fast as possible" if not args.rate else f"{args.rate:g}x"
        _say(args, f"replaying {len(messages)} messages of {args.path} under {bus.keys.prefix}/ at {rate}"
                   + (", looping (Ctrl-C stops)" if args.loop else ""))
        subscribed = player.wait_for_subscriber(args.wait_for_subscriber) if args.wait_for_subscriber else None
        if subscribed is False:
            _say(args, f"nobody listens after {args.wait_for_subscriber:g} s; replaying anyway")
        stats = player.play(args.rate, stop, loop=args.loop)
        player.drain()
    result = {"run_id": run_id, "key_prefix": f"dmosim/{run_id}", "selected": len(messages),
              "published": stats.published, "loops": stats.loops, "seconds": round(stats.seconds, 3),
              "msgs_per_s": round(stats.published / stats.seconds) if stats.seconds > 0 else None,
              "interrupted": stop.is_set(), "subscribed": subscribed}
    if args.json:
        print_json(result)
    else:
        print(f"replayed {stats.published} messages under {result['key_prefix']}/ in {stats.seconds:.2f} s"
              + (f" ({stats.loops} loops)" if args.loop else "") + (" (interrupted)" if stop.is_set() else ""))
    return 0


def _say(args, text: str) -> None:
    if not args.quiet:
        progress(text)


def _as_dmo(args, rec: Recording, run_id: str) -> int:
    """``--as-dmo``: the recorded day played to a live agent, the DMO's machine running its market
    (replay/recorded.py)."""
    from dmo.replay.recorded import RecordedMarket  # noqa: PLC0415  (the DMO's machine, only for --as-dmo)

    try:
        day = recorded_day(rec, args.day)
        rule = recorded_rule(day, Trust(everything=args.trust_rules))  # said now, before anything starts
    except UntrustedRule as err:
        raise untrusted(f"{args.path}: {day.market_day} was settled by {err.spec}", err.spec, "") from None
    except ResettleError as exc:
        raise UsageError(str(exc)) from None
    agent = args.agent or sorted(day.awards)[0]
    try:
        check_agent_id(agent)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if agent not in day.awards:
        raise UsageError(f"{args.path}: no award recorded for {agent} (awarded: {', '.join(sorted(day.awards))})")
    out = recording_path(args.record, args.overwrite) if args.record else None
    try:
        market = RecordedMarket(rec, day, agent, rule)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    scratch = Path(tempfile.mkdtemp(prefix="dmosim-replay-"))  # credentials it makes live as long as the replay
    try:
        credentials_for(args, run_id, [agent], dmo_client=False, scratch=scratch)
        return _serve(args, rec, day, agent, market, out, run_id)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _serve(args, rec: Recording, day, agent: str, market, out: Path | None, run_id: str) -> int:
    """The DMO's side of ``--as-dmo`` on the bus, with its own recorder when ``out`` names a file."""
    from dmo.operator.day import MarketDay  # noqa: PLC0415  (the DMO's machine loads the feeder's clearing)
    from dmo.operator.machine import NobodyRegistered  # noqa: PLC0415
    from dmo.replay.recorded import render, replay_config, replay_result  # noqa: PLC0415

    config = bus_config(args, "router", run_id=run_id)
    endpoint = (config.listen or config.connect or ("zenoh's default",))[0]
    _say(args, f"playing the DMO of {args.path} ({day.market_day}) under dmosim/{run_id}/ for agent {agent}; start "
               f"it with: dmosim agent --experiment EXPERIMENT --id {agent} --run-id {run_id} --market-day "
               f"{day.market_day} --connect {endpoint}" + (f" --auth-dir {args.auth_dir}" if args.auth_dir else
                                                           " --insecure")
               + ", EXPERIMENT being the run's experiment.toml (in its run directory; dmosim info prints it)")
    writer = RecordingWriter(out, run_id) if out else None
    recorder_stop, recorder_thread = threading.Event(), None
    try:
        with Bus(run_id, DMO, config) as bus:
            if writer is not None:
                meta = {k: v for k, v in rec.metadata.items() if k in ("config", "seed")}
                writer.start({**meta, "command": "dmosim replay --as-dmo", "source": str(args.path),
                              "source_run_id": rec.run_id, "market_day": day.market_day, "agents": agent},
                             [(a.name, a.media_type, a.data) for a in rec.attachments])
                recorder = Recorder(bus, writer, announce=False)
                recorder.start(backfill=False)  # this process is the day's DMO: nothing to ask it
                recorder_thread = threading.Thread(target=recorder.run, args=(recorder_stop,), name="recorder")
                recorder_thread.start()
            try:
                run = MarketDay(bus, replay_config(day, args.timeout), market=market).run()
            except NobodyRegistered:
                raise RuntimeError(f"agent {agent} did not register within {args.timeout:g} s") from None
            result = replay_result(run, market, run_id)
    finally:
        recorder_stop.set()
        if recorder_thread is not None:
            recorder_thread.join()
        elif writer is not None:
            writer.close()
    result["recording"] = str(out.resolve()) if out else None
    if args.json:
        print_json(result)
    else:
        print(render(result))
    return 0
