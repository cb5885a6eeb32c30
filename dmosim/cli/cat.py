"""``dmosim cat PATH``: every recorded message as one JSON line, in log-time order, as ``mcap cat --json`` prints.

Each line is ``{"log_time_ns", "key" (relative to the run prefix), "kind", "message" (the payload as JSON)}``; a
payload the recorder filed as invalid has ``"invalid": {"code", "reason"}`` and ``"payload_base64"`` (the bytes as
they arrived) instead of ``"message"``. ``--topics`` selects keys as ``dmosim replay --topics`` does.
"""

from __future__ import annotations

import argparse
import base64
import json
import sys

from messages.recording import RecordedMessage, select

from ..arguments import market_day
from .flags import RECORDING_HELP, load_recording, recorded_day_flag

HELP = "print every message of a recording or a run directory as one JSON line, in log-time order"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help=RECORDING_HELP)
    p.add_argument("--topics", action="append", default=[], metavar="PATTERN",
                   help="only keys matching this pattern, relative to the run prefix, e.g. 'dmo/*' or "
                        "'agent/*/meter' (* one level, ** any; repeatable)")
    p.add_argument("--day", type=market_day, metavar="YYYY-MM-DD",
                   help="only the messages of this market day (a recording may hold several)")


def line(m: RecordedMessage) -> dict:
    """One recorded message as its JSON line's object."""
    out = {"log_time_ns": m.log_time, "key": m.relative_key, "kind": m.kind}
    if m.invalid is None:
        try:
            out["message"] = json.loads(m.payload)
            return out
        except (ValueError, RecursionError):  # a valid payload is JSON; this guards a file written by another tool
            pass
    code, reason = m.invalid or ("not_json", "not JSON")
    out["invalid"] = {"code": code, "reason": reason}
    out["payload_base64"] = base64.b64encode(m.payload).decode("ascii")
    return out


def run(args) -> int:
    rec = load_recording(args.path)
    recorded_day_flag(rec, args.day)
    if rec.cut_note:
        print(f"warning: {rec.path}: {rec.cut_note}; printing what was recorded before the cut", file=sys.stderr)
    write = sys.stdout.write
    for m in select(rec, args.topics, market_day=args.day):
        write(json.dumps(line(m), separators=(",", ":"), ensure_ascii=False) + "\n")
    sys.stdout.flush()
    return 0
