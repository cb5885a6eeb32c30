"""Write one run's recording: each payload on its key's channel (or the invalid channel), in chunks closed often.

Crash safety: the writer closes its chunk and hands it to the OS every ``chunk_messages`` messages or
``flush_interval_s`` seconds, whichever comes first, so a recorder killed with SIGKILL loses at most the chunk it
had open (``reader.read_recording`` reads every complete record of such a file). The layout is in layout.py.
"""

from __future__ import annotations

import base64
import collections
import datetime as _dt
import hashlib
import json
import mimetypes
import os
import tempfile
import time
from pathlib import Path
from typing import BinaryIO, Iterable, Mapping

from mcap.data_stream import RecordBuilder
from mcap.records import ChunkIndex
from mcap.writer import CompressionType, Writer

from ..codec import MAX_PAYLOAD_BYTES, MessageError, decode
from ..keys import Keys, parse_key
from ..schemas import SCHEMA_VERSION, SCHEMAS
from .layout import (ANY_SCHEMA, ANY_SCHEMA_NAME, CHUNK_BYTES, CHUNK_MESSAGES, FLUSH_INTERVAL_S, INVALID_KEY,
                     INVALID_SCHEMA, INVALID_SCHEMA_NAME, KEPT_INVALID_BYTES, KEPT_INVALID_TOTAL, MESSAGE_ENCODING,
                     METADATA_NAME, SCHEMA_ENCODING, library, versions)


class RecordingWriter:
    """One MCAP file of one run, written from one thread (the mcap writer is not thread-safe).

    ``write(key, payload, log_time)`` files a payload on its key's channel (or the invalid channel); ``tick()``
    closes the open chunk when it holds ``chunk_messages`` messages, ``chunk_bytes`` bytes or is
    ``flush_interval_s`` old; ``close()`` writes the summary section and the footer.
    """

    def __init__(self, out: str | os.PathLike, run_id: str, *, chunk_messages: int = CHUNK_MESSAGES,
                 flush_interval_s: float = FLUSH_INTERVAL_S, chunk_bytes: int = CHUNK_BYTES):
        self.keys = Keys(run_id)
        self.path = Path(out)
        self.chunk_messages, self.flush_interval_s, self.chunk_bytes = chunk_messages, flush_interval_s, chunk_bytes
        self._file = open(self.path, "wb")  # noqa: SIM115  (closed by close())
        # mcap closes a chunk by itself past chunk_size; ours closes it first, so that every closed chunk also
        # reaches the OS at once (mcap's own would wait in the file buffer).
        self._mcap = Writer(self._file, chunk_size=4 * chunk_bytes, compression=CompressionType.ZSTD)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str | None]] = {}  # key -> (channel id, kind)
        self._invalid_channel: int | None = None
        self.counts: collections.Counter[str] = collections.Counter()  # per key (invalid ones under their key)
        self.messages = 0
        self.invalid = 0
        self._invalid_kept = 0  # bytes of invalid payloads kept in the file
        self._pending = 0
        self._pending_bytes = 0
        self._chunk_opened = time.monotonic()
        self._closed = False
        self._spill = tempfile.TemporaryFile()  # noqa: SIM115  (closed by close()) the closed chunks' indexes

    def start(self, metadata: Mapping[str, str] | None = None,
              attachments: Iterable[tuple[str, str, bytes]] = ()) -> None:
        """Header, the ``dmosim`` metadata record and the attachments (name, media type, bytes), on disk at once."""
        self._mcap.start(profile="", library=library())
        record = {"schema_version": str(SCHEMA_VERSION), "run_id": self.keys.run_id, "key_prefix": self.keys.prefix,
                  "recorder_started_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
                  "versions": json.dumps(versions(), sort_keys=True)}
        record.update({str(k): str(v) for k, v in (metadata or {}).items()})
        self._mcap.add_metadata(METADATA_NAME, record)
        now = time.time_ns()
        for name, media_type, data in attachments:
            self._mcap.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=data)
        self._mcap.flush()

    def add_metadata(self, name: str, record: Mapping[str, str]) -> None:
        """Another metadata record (e.g. ``BACKFILL_METADATA``: what a late recorder was given by the DMO)."""
        self._mcap.add_metadata(name, {str(k): str(v) for k, v in record.items()})

    def write(self, key: str, payload: bytes, log_time: int) -> bool:
        """File one received payload; returns whether it was valid for its key."""
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self._register(key)
        channel_id, kind = channel
        if channel_id == 0:
            return self._write_invalid(key, payload, log_time, "wrong_key", "the recorder's own key")
        seq = 0
        if kind is not None:
            try:
                msg = decode(payload, expected_kind=kind)
            except MessageError as err:
                return self._write_invalid(key, payload, log_time, err.code, err.reason)
            publish_time, seq = msg.sent_at or log_time, msg.seq
        else:
            if len(payload) > MAX_PAYLOAD_BYTES:  # the limit decode applies to every kind, on a key of none
                return self._write_invalid(key, payload, log_time, "oversize",
                                           f"payload is {len(payload)} bytes, over the {MAX_PAYLOAD_BYTES}-byte limit")
            try:
                data = json.loads(payload)
            except (ValueError, RecursionError):
                return self._write_invalid(key, payload, log_time, "not_json", "not JSON")
            sent_at = data.get("sent_at") if isinstance(data, dict) else None
            publish_time = sent_at if type(sent_at) is int and 0 < sent_at < 2**63 else log_time
        self._add(channel_id, key, payload, log_time, publish_time, seq)
        return True

    def _write_invalid(self, key: str, payload: bytes, log_time: int, code: str, reason: str) -> bool:
        if self._invalid_channel is None:
            schema = self._schema(INVALID_SCHEMA_NAME, INVALID_SCHEMA)
            self._invalid_channel = self._mcap.register_channel(f"{self.keys.prefix}/{INVALID_KEY}", MESSAGE_ENCODING,
                                                                schema, {"kind": "invalid_payload"})
        # Kept whole up to KEPT_INVALID_BYTES (a garbled honest message replays as the same fault), a larger one to
        # its first KEPT_INVALID_BYTES, and none of it once the file holds KEPT_INVALID_TOTAL of such bytes: what a
        # peer sends cannot make the file expand past what the reader accepts. Its size and SHA-256 are kept always.
        room = max(0, KEPT_INVALID_TOTAL - self._invalid_kept)
        kept = payload[:min(KEPT_INVALID_BYTES, room)]
        self._invalid_kept += len(kept)
        wrapped = json.dumps({"key": key, "code": code, "reason": reason, "payload_size": len(payload),
                              "payload_sha256": hashlib.sha256(payload).hexdigest(),
                              "payload_base64": base64.b64encode(kept).decode("ascii")}).encode()
        self.invalid += 1
        self._add(self._invalid_channel, key, wrapped, log_time, log_time, 0)
        return False

    def _add(self, channel_id: int, key: str, data: bytes, log_time: int, publish_time: int, seq: int) -> None:
        self._mcap.add_message(channel_id, log_time=log_time, data=data, publish_time=publish_time,
                               sequence=seq & 0xFFFFFFFF)  # MCAP's sequence is 32-bit
        self.messages += 1
        self.counts[key] += 1
        self._pending += 1
        self._pending_bytes += len(data)
        if self._pending >= self.chunk_messages or self._pending_bytes >= self.chunk_bytes:
            self.flush()

    def _register(self, key: str) -> tuple[int, str | None]:
        if key == f"{self.keys.prefix}/{INVALID_KEY}":
            return 0, None
        try:
            kind = parse_key(key).kind
        except MessageError:
            kind = None
        if kind is None:
            schema = self._schema(ANY_SCHEMA_NAME, ANY_SCHEMA)
        else:
            schema = self._schema(f"dmosim.{kind}", SCHEMAS[kind])
        return self._mcap.register_channel(key, MESSAGE_ENCODING, schema, {"kind": kind or ""}), kind

    def _schema(self, name: str, schema: dict) -> int:
        if name not in self._schemas:
            self._schemas[name] = self._mcap.register_schema(name, SCHEMA_ENCODING,
                                                             json.dumps(schema, sort_keys=True).encode())
        return self._schemas[name]

    def tick(self, now: float | None = None) -> None:
        """Close the open chunk if it is ``flush_interval_s`` old (call this at least that often)."""
        if self._pending and (now if now is not None else time.monotonic()) - self._chunk_opened >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and hand everything written to the OS (not fsync: a killed process loses
        nothing the OS has; a power cut is another matter)."""
        self._mcap.flush()
        _spill_last_chunk_index(self._mcap, self._spill)
        self._pending = self._pending_bytes = 0
        self._chunk_opened = time.monotonic()

    def close(self) -> None:
        """The last chunk, the summary section (schemas, channels, statistics, indexes) and the footer."""
        if self._closed:
            return
        self._closed = True
        try:
            self._mcap.finish()
        finally:
            self._file.close()
            self._spill.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_attachments(paths: Iterable[str | os.PathLike]) -> list[tuple[str, str, bytes]]:
    """The files ``paths`` as attachments (name, media type, bytes) for ``RecordingWriter.start``: each by its file
    name, made unique where two from different directories share one. A file that cannot be read is an OSError."""
    out, names = [], set()
    for path in paths:
        p = Path(path)
        data = p.read_bytes()
        name, n = p.name, 1
        while name in names:
            n += 1
            name = f"{p.stem}-{n}{p.suffix}"
        names.add(name)
        media = "application/toml" if p.suffix == ".toml" else mimetypes.guess_type(p.name)[0] or "application/octet-stream"
        out.append((name, media, data))
    return out


class WrittenChunkIndex:
    """A closed chunk's index kept on disk as the bytes the summary section will hold (which is how mcap's writer
    writes it), read back when the summary is written.

    The writer keeps every chunk's index until the summary (it needs them there); as a ``ChunkIndex`` an index holds
    a dict of the chunk's channels, about 100 bytes each, as bytes 10, and chunks close every second: over a week of
    100 agents the indexes grew the recorder by about 0.5 MiB a day in memory (docs/benchmarks.md, "week"). Here
    memory keeps where the bytes are in a scratch file (``spill``), about 60 bytes a chunk."""

    __slots__ = ("spill", "offset", "length")

    def __init__(self, index: ChunkIndex, spill: BinaryIO):
        builder = RecordBuilder()
        index.write(builder)
        record = builder.end()
        self.spill, self.offset, self.length = spill, spill.seek(0, os.SEEK_END), len(record)
        spill.write(record)

    def write(self, stream: RecordBuilder) -> None:
        self.spill.seek(self.offset)
        stream.write(self.spill.read(self.length))


def _spill_last_chunk_index(writer: Writer, spill: BinaryIO) -> None:
    """The index of the chunk ``writer`` closed last, as a ``WrittenChunkIndex`` in ``spill`` (the list is mcap's own,
    private: tests/messages/test_recording.py checks it is still there and what the summary reads back)."""
    indexes = getattr(writer, "_Writer__chunk_indices", None)
    if indexes and isinstance(indexes[-1], ChunkIndex):
        indexes[-1] = WrittenChunkIndex(indexes[-1], spill)
