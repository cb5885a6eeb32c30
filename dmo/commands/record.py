"""``dmosim record``: the recorder role: every message under one run prefix, as it arrived, into one MCAP file."""

from __future__ import annotations

import logging
import mimetypes
import signal
import threading
from pathlib import Path

from messages.keys import check_run_id
from messages.recording import RecordingWriter, Recorder
from messages.transport import Bus

from ..console import UsageError
from .roles import _bus_config, setup_logging

log = logging.getLogger("dmosim.recorder")


def check_output(path: str, overwrite: bool) -> Path:
    """Where a recording may go: an existing directory, and no file there unless ``overwrite``."""
    out = Path(path)
    if out.is_dir():
        raise UsageError(f"{path} is a directory; give a file name, e.g. {out / 'day.mcap'}")
    if not out.parent.is_dir():
        raise UsageError(f"cannot write {path}: directory {out.parent} does not exist")
    if out.exists() and not overwrite:
        raise UsageError(f"{path} exists; remove it, choose another name or pass --overwrite")
    return out


def parse_meta(items: list[str]) -> dict[str, str]:
    meta = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--meta {item!r}: expected KEY=VALUE")
        meta[key.strip()] = value
    return meta


def read_attachments(paths: list[str]) -> list[tuple[str, str, bytes]]:
    out, names = [], set()
    for path in paths:
        p = Path(path)
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise UsageError(f"--attach {path}: {exc.strerror or exc}") from None
        name, n = p.name, 1
        while name in names:  # two files of the same name from different directories
            n += 1
            name = f"{p.stem}-{n}{p.suffix}"
        names.add(name)
        media = "application/toml" if p.suffix == ".toml" else mimetypes.guess_type(p.name)[0] or "application/octet-stream"
        out.append((name, media, data))
    return out


def run(args) -> int:
    setup_logging("recorder", args.quiet)
    try:
        check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    out = check_output(args.out, args.overwrite)
    meta, attachments = parse_meta(args.meta), read_attachments(args.attach)
    config = _bus_config(args, "client", "recorder")

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())  # finish the file: the last chunk, the summary, the footer
    writer = RecordingWriter(out, args.run_id, chunk_messages=args.chunk_messages, flush_interval_s=args.flush_interval)
    try:
        writer.start(meta, attachments)
        with Bus(args.run_id, "recorder", config, announce=False) as bus:
            recorder = Recorder(bus, writer)
            recorder.start()
            log.info("recording %s/** to %s", bus.keys.prefix, out)
            if args.ready_file:
                Path(args.ready_file).write_text(str(out) + "\n")
            recorder.run(stop)
    finally:
        writer.close()
    log.info("recorded %d messages (%d invalid) on %d keys to %s; %.3f s from the first receipt to the last write",
             writer.messages, writer.invalid, len(writer.counts), out, recorder.busy_s)
    return 0
