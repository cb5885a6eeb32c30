"""``dmosim record``: the recorder role: every message under one run prefix, as it arrived, into one MCAP file."""

from __future__ import annotations

import argparse
import faulthandler
import logging
import signal
import threading
import time
from pathlib import Path

from messages.keys import check_run_id
from messages.recording import (BACKFILL_METADATA, CHUNK_MESSAGES, FLUSH_INTERVAL_S, Recorder, RecordingWriter,
                                read_attachments)
from messages.transport import Bus

from ..arguments import nonneg_float, positive_int
from ..console import UsageError
from .flags import add_bus_flags, bus_config, recording_path, setup_logging

HELP = "the recorder role: every message of one run into an MCAP file"
log = logging.getLogger("dmosim.recorder")
STUCK_S = 30.0  # a recorder this long in stopping is stuck (a 200-agent day's recorder stops in well under 1 s)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="PATH", help="the MCAP file to write")
    p.add_argument("--run-id", default="day", help="the run whose prefix is recorded (default: day)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                   help="add to the recording's metadata record (repeatable)")
    p.add_argument("--attach", action="append", default=[], metavar="PATH",
                   help="store a file (case, fleet) in the recording (repeatable)")
    p.add_argument("--chunk-messages", type=positive_int, default=CHUNK_MESSAGES,
                   help=f"close a chunk after this many messages (default: {CHUNK_MESSAGES})")
    p.add_argument("--flush-interval", type=nonneg_float, default=FLUSH_INTERVAL_S, metavar="S",
                   help=f"close a chunk at least this often, seconds (default: {FLUSH_INTERVAL_S:g})")
    p.add_argument("--ready-file", metavar="PATH", help="write this file once the recorder listens")
    p.add_argument("--no-backfill", action="store_true",
                   help="record only what arrives from now on; by default the recorder first asks the DMO for what "
                        "the run said before it joined (docs/recording.md, \"Late joiners\")")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_bus_flags(p, "client")


def parse_meta(items: list[str]) -> dict[str, str]:
    meta = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--meta {item!r}: expected KEY=VALUE")
        meta[key.strip()] = value
    return meta


def run(args) -> int:
    setup_logging("recorder", args.quiet)
    try:
        check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = recording_path(args.out, args.overwrite)
    meta = parse_meta(args.meta)
    try:
        attachments = read_attachments(args.attach)
    except OSError as exc:
        raise UsageError(f"--attach {exc.filename}: {exc.strerror or exc}") from None
    config = bus_config(args, "client", "recorder")  # a reader of another name logs in and announces as --user

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: _stopping(stop))
    writer = RecordingWriter(out, args.run_id, chunk_messages=args.chunk_messages, flush_interval_s=args.flush_interval)
    try:
        writer.start(meta, attachments)
        with Bus(args.run_id, args.user or "recorder", config, announce=False) as bus:
            recorder = Recorder(bus, writer)
            if recorder.start(backfill=not args.no_backfill):
                writer.add_metadata(BACKFILL_METADATA, {"messages": recorder.backfilled, "source": "dmo history",
                                                        "joined_at_ns": time.time_ns()})
            log.info("recording %s/** to %s", bus.keys.prefix, out)
            if args.ready_file:
                Path(args.ready_file).write_text(str(out) + "\n")
            recorder.run(stop)
            log.info("recorded %d messages (%d invalid) on %d keys to %s, %d of them caught up from the DMO after the "
                     "network lost them; %.3f s from the first receipt to the last write", writer.messages,
                     writer.invalid, len(writer.counts), out, recorder.caught_up, recorder.busy_s)
    finally:
        writer.close()
    return 0


def _stopping(stop: threading.Event) -> None:
    """Finish the file (the last chunk, the summary, the footer) and leave; a recorder still there ``STUCK_S`` later
    writes where each of its threads is to its log and exits 1 (its launcher then looks at the file itself)."""
    stop.set()
    faulthandler.dump_traceback_later(STUCK_S, exit=True)

