"""The DMO's journal read as a recording: the run's traffic as the DMO journaled it (every payload it sent or
received, docs/faults.md), in the in-memory form of ``messages.recording.Recording``, so that a run whose recorder
failed still gets its tables and its ``--from`` comparison from what the DMO saw."""

from __future__ import annotations

import json
from pathlib import Path

from dmo.operator.journal import traffic
from messages import Keys, MessageError, decode, parse_key, relative_key
from messages.recording import RecordedMessage, Recording

JOURNAL_LIBRARY = "dmosim journal"  # the ``library`` of a recording read from a journal


def journal_recording(path: Path, run_id: str, metadata: dict[str, str]) -> Recording:
    """The traffic of the journal at ``path`` (of run ``run_id``) as a recording with ``metadata`` (as ``dmosim
    run`` gives its recorder: ``market_day``, ``days``, ``agents``); each payload filed as the recorder files it,
    valid for its key or invalid with its code and reason. A line cut by a killed DMO ends the journal there."""
    entries = []
    with open(path, encoding="utf-8", errors="replace") as f:
        next(f, None)  # the head: which run and day the journal is of
        for line in f:
            try:
                entries.append(json.loads(line))
            except ValueError:
                break
    prefix, size = Keys(run_id).prefix, path.stat().st_size
    return Recording(path=str(path), size=size, bytes_read=size, library=JOURNAL_LIBRARY, complete=True,
                     metadata={**metadata, "run_id": run_id, "key_prefix": prefix},
                     messages=[recorded(key, payload, at, prefix) for key, payload, at in traffic(entries)])


def recorded(key: str, payload: bytes, at: int, prefix: str) -> RecordedMessage:
    """One payload as the recorder would have recorded it, received at ``at`` (ns)."""
    try:
        kind = parse_key(key).kind
    except MessageError:
        kind = None
    publish_time, seq, invalid = at, 0, None
    if kind is not None:
        try:
            msg = decode(payload, expected_kind=kind)
            publish_time, seq = msg.sent_at or at, msg.seq
        except MessageError as err:
            invalid = (err.code, err.reason)
    return RecordedMessage(key, relative_key(key, prefix), kind, payload, at, publish_time, seq, invalid)
