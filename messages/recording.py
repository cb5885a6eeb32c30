"""MCAP recordings of a run: the recorder that writes every payload as it arrived, and a reader that survives a cut file.

A recording is self-describing and opens in any MCAP reader with no code of ours:

- one channel per key expression, topic = the key as it travelled (``dmosim/<run>/dmo/grid``), message encoding
  ``json``, schema encoding ``jsonschema`` with the JSON Schema of the key's kind (``schemas.json_schema``);
- a payload that fails its key's schema (not JSON, wrong kind, a missing field...) is never written on that
  channel, so every message of a channel validates against the channel's schema. It goes, with the reason it
  failed, to the one channel ``<prefix>/recorder/invalid`` (schema ``dmosim.invalid_payload``: the key, the
  rejection code and reason, and the payload in base64). Payloads the DMO refuses for what they mean (late,
  duplicate, unregistered...) are valid and stay on their key's channel; the DMO's ``Rejection`` on
  ``dmo/rejected`` says which and why;
- ``log_time`` is the recorder's receive time, ``publish_time`` the sender's ``sent_at``, ``sequence`` its ``seq``;
- zstd-compressed chunks, message and chunk indexes, a summary section with statistics;
- one metadata record ``dmosim`` (run id, key prefix, message schema version, versions, and what the caller adds:
  configuration, seed, market day, agents) and the case and fleet files as attachments, both written first so
  that a cut file still has them.

Crash safety: the recorder closes its chunk and hands it to the OS every ``chunk_messages`` messages or
``flush_interval_s`` seconds, whichever comes first, so a recorder killed with SIGKILL loses at most the chunk it
had open. ``read_recording`` reads every complete record of such a file and says where it was cut.
"""

from __future__ import annotations

import base64
import collections
import datetime as _dt
import json
import logging
import os
import queue
import re
import sys
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata as _metadata
from pathlib import Path
from typing import Callable, Iterable, Mapping

from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from .codec import MessageError, decode
from .keys import ROOT, Keys, parse_key
from .schemas import SCHEMA_VERSION, SCHEMAS

log = logging.getLogger("dmosim.recorder")

MAGIC = b"\x89MCAP0\r\n"
MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
METADATA_NAME = "dmosim"
INVALID_KEY = "recorder/invalid"        # relative to the run prefix; not a key anyone publishes on
INVALID_SCHEMA_NAME = "dmosim.invalid_payload"
ANY_SCHEMA_NAME = "dmosim.any"
CHUNK_MESSAGES = 500
FLUSH_INTERVAL_S = 1.0
CHUNK_BYTES = 1 << 20
_DRAFT = "https://json-schema.org/draft/2020-12/schema"

# A payload on a key outside the layout (no kind): any JSON value.
ANY_SCHEMA = {"$schema": _DRAFT, "$id": f"urn:dmosim:any:v{SCHEMA_VERSION}", "title": "Unchecked",
              "description": "a JSON payload on a key outside the dmosim layout, recorded as it arrived"}
INVALID_SCHEMA = {
    "$schema": _DRAFT, "$id": f"urn:dmosim:invalid_payload:v{SCHEMA_VERSION}", "title": "InvalidPayload",
    "description": "a payload that failed its key's schema, recorded with the reason",
    "type": "object", "additionalProperties": False,
    "required": ["key", "code", "reason", "payload_size", "payload_base64"],
    "properties": {"key": {"type": "string"}, "code": {"type": "string"}, "reason": {"type": "string"},
                   "payload_size": {"type": "integer", "minimum": 0},
                   "payload_base64": {"type": "string", "contentEncoding": "base64"}},
}
_SCHEMA_ID = re.compile(r"^urn:dmosim:[a-z_]+:v([0-9]+)$")


def versions() -> dict[str, str]:
    """Versions of what shapes a recording's contents: this package, Python and the libraries on the path."""
    out = {"dmosim": _version("dmosim"), "python": sys.version.split()[0]}
    for name in ("mcap", "eclipse-zenoh", "pydantic", "numpy", "cvxpy", "highspy"):
        out[name] = _version(name)
    return out


def _version(dist: str) -> str:
    try:
        return _metadata.version(dist)
    except _metadata.PackageNotFoundError:
        return "unknown"


def library() -> str:
    return f"dmosim {_version('dmosim')} (message schemas v{SCHEMA_VERSION}); mcap-python {_version('mcap')}"


# --- writing ----------------------------------------------------------------------------------------------------

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
        self._pending = 0
        self._pending_bytes = 0
        self._chunk_opened = time.monotonic()
        self._closed = False

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
        wrapped = json.dumps({"key": key, "code": code, "reason": reason, "payload_size": len(payload),
                              "payload_base64": base64.b64encode(payload).decode("ascii")}).encode()
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

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Recorder:
    """Records every payload under one run prefix, as it arrived, valid or not: Zenoh's threads only enqueue,
    and ``run`` writes on the calling thread until ``stop`` is set, then drains the queue and closes the file.

    The liveliness token ``alive/recorder`` is declared after the subscription, so whoever sees the recorder
    present (the DMO waits for it) knows that it is already listening.
    """

    def __init__(self, bus, writer: RecordingWriter, announce: bool = True):
        self.bus, self.writer, self.announce = bus, writer, announce
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._subscription = None
        self._token = None
        self.first_received_ns = 0   # receipt of the first message, and the end of the last write: the span the
        self.last_written_ns = 0     # recorder kept up with (its sustained rate is messages / span)

    def start(self) -> None:
        self._subscription = self.bus.subscribe_raw(self.bus.keys.everything(),
                                                    lambda key, payload, at: self._queue.put((key, payload, at)))
        if self.announce:
            self._token = self.bus.session.liveliness().declare_token(self.bus.keys.alive("recorder"))

    def run(self, stop: threading.Event, on_write: Callable[[str, bool], None] | None = None) -> None:
        writer, q = self.writer, self._queue
        try:
            while not stop.is_set():
                try:
                    item = q.get(timeout=min(0.1, writer.flush_interval_s))
                except queue.Empty:
                    writer.tick()
                    continue
                self._write(*item, on_write)
                for _ in range(writer.chunk_messages):  # drain a burst before looking at the clock again
                    try:
                        item = q.get_nowait()
                    except queue.Empty:
                        break
                    self._write(*item, on_write)
                writer.tick()
        finally:
            self.stop()
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                self._write(*item, on_write)
            writer.close()

    def _write(self, key: str, payload: bytes, at: int, on_write) -> None:
        valid = self.writer.write(key, payload, at)
        self.first_received_ns = self.first_received_ns or at
        self.last_written_ns = time.time_ns()
        if on_write is not None:
            on_write(key, valid)

    @property
    def busy_s(self) -> float:
        return max(0.0, (self.last_written_ns - self.first_received_ns) / 1e9)

    def stop(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # the session may be closing already
                log.debug("could not undeclare the recorder's token", exc_info=True)
        subscription, self._subscription = self._subscription, None
        if subscription is not None:
            subscription.close()


# --- reading ----------------------------------------------------------------------------------------------------

class RecordingError(ValueError):
    """A file that cannot be read as a recording: ``str(err)`` is one line naming the file and the problem."""


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded payload. ``key`` is the key it travelled on (under the recorded run's prefix), ``payload`` the
    bytes as they arrived; ``invalid`` is (code, reason) for a payload that failed its key's schema."""

    key: str
    relative_key: str
    kind: str | None
    payload: bytes
    log_time: int
    publish_time: int
    sequence: int
    invalid: tuple[str, str] | None = None


@dataclass
class ChannelInfo:
    id: int
    topic: str
    relative_key: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    messages: int = 0


@dataclass
class Recording:
    """Everything a file holds, read front to back. ``complete`` is False for a cut file (``cut_note`` says
    where); every complete record before the cut is here."""

    path: str
    size: int
    library: str = ""
    profile: str = ""
    metadata: dict[str, str] = field(default_factory=dict)
    other_metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: list[Attachment] = field(default_factory=list)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    messages: list[RecordedMessage] = field(default_factory=list)
    chunks: int = 0
    compression: set[str] = field(default_factory=set)
    statistics: Statistics | None = None
    complete: bool = False
    bytes_read: int = 0
    cut_reason: str | None = None

    @property
    def prefix(self) -> str:
        return self.metadata.get("key_prefix") or _prefix_of(c.topic for c in self.channels.values())

    @property
    def run_id(self) -> str:
        return self.metadata.get("run_id") or self.prefix.partition("/")[2]

    @property
    def schema_version(self) -> int | None:
        try:
            return int(self.metadata["schema_version"])
        except (KeyError, ValueError):
            return None

    @property
    def cut_note(self) -> str | None:
        if self.complete:
            return None
        pct = 100.0 * self.bytes_read / self.size if self.size else 0.0
        return (f"file cut after {len(self.messages)} messages ({pct:.1f}% of its {self.size} bytes readable"
                f"{': ' + self.cut_reason if self.cut_reason else ''})")

    def in_log_order(self) -> list[RecordedMessage]:
        return sorted(self.messages, key=lambda m: m.log_time)

    def decoded(self, kind: str) -> list[tuple[RecordedMessage, object]]:
        """The valid messages of one kind with their decoded form, in log order."""
        out = []
        for m in self.in_log_order():
            if m.kind == kind and m.invalid is None:
                try:
                    out.append((m, decode(m.payload, expected_kind=kind)))
                except MessageError:
                    continue
        return out


def _prefix_of(topics: Iterable[str]) -> str:
    for topic in topics:
        parts = topic.split("/")
        if len(parts) > 2 and parts[0] == ROOT:
            return f"{parts[0]}/{parts[1]}"
    return ""


def read_recording(path: str | os.PathLike) -> Recording:
    """Read a recording front to back, tolerating a cut or torn end: whatever complete records precede the damage
    are returned, with ``complete`` False. Raises RecordingError (one line) for a file that is not MCAP, is cut
    before its header, or was written with a newer message schema version than this dmosim reads."""
    name = str(path)
    try:
        f = open(path, "rb")  # noqa: SIM115
    except FileNotFoundError:
        raise RecordingError(f"{name}: no such file") from None
    except OSError as exc:
        raise RecordingError(f"{name}: cannot read: {exc.strerror or exc}") from None
    with f:
        size = os.fstat(f.fileno()).st_size
        magic = f.read(len(MAGIC))
        if magic != MAGIC:
            if magic and MAGIC.startswith(magic):
                raise RecordingError(f"{name}: file cut after {len(magic)} bytes, before its MCAP header")
            raise RecordingError(f"{name}: not an MCAP file" + (" (empty)" if not magic else " (bad magic bytes)"))
        f.seek(0)
        rec = Recording(path=name, size=size, bytes_read=len(MAGIC))
        _Scan(rec).run(StreamReader(f, emit_chunks=True, record_size_limit=max(size, 1)), f)
    if not rec.library and not rec.profile and not rec.messages and rec.bytes_read <= len(MAGIC):
        raise RecordingError(f"{name}: file cut after {size} bytes, before its MCAP header was complete")
    prefix = rec.prefix
    for channel in rec.channels.values():
        channel.relative_key = _relative(channel.topic, prefix)
    return rec


class _Scan:
    """Fills a Recording from the records of a stream, stopping at the first record that cannot be read whole."""

    def __init__(self, rec: Recording):
        self.rec = rec
        self.raw_channels: dict[int, Channel] = {}
        self.in_data = True

    def run(self, reader: StreamReader, f) -> None:
        rec = self.rec
        records = reader.records
        while True:
            try:
                record = next(records)
            except StopIteration:
                rec.complete = True
                rec.bytes_read = rec.size
                return
            except RecordingError:
                raise
            except Exception as exc:  # EndOfFile, struct.error, InvalidMagic, a record too long for the file...
                rec.cut_reason = _why(exc)
                return
            try:
                self.record(record)
            except RecordingError:
                raise
            except Exception as exc:  # a torn chunk (zstd or CRC error), a message on an unknown channel
                rec.cut_reason = _why(exc)
                return
            if not isinstance(record, Footer):
                rec.bytes_read = f.tell()

    def record(self, record) -> None:
        rec = self.rec
        if isinstance(record, Header):
            rec.library, rec.profile = record.library, record.profile
        elif isinstance(record, Metadata):
            if record.name == METADATA_NAME:
                rec.metadata = dict(record.metadata)
                _check_version(rec.path, rec.metadata.get("schema_version"))
            else:
                rec.other_metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Attachment):
            rec.attachments.append(record)
        elif isinstance(record, Chunk):
            parts = breakup_chunk(record, validate_crc=True)  # a torn chunk raises here, before any of it is kept
            rec.chunks += 1
            rec.compression.add(record.compression or "none")
            for part in parts:
                self.record(part)
        elif isinstance(record, Schema):
            if record.id not in rec.schemas:
                rec.schemas[record.id] = record
                _check_schema_version(rec.path, record)
        elif isinstance(record, Channel):
            if record.id not in self.raw_channels:
                self.raw_channels[record.id] = record
                schema = rec.schemas.get(record.schema_id)
                rec.channels[record.id] = ChannelInfo(
                    record.id, record.topic, "", record.message_encoding,
                    schema.name if schema else "", schema.encoding if schema else "")
        elif isinstance(record, Message):
            if self.in_data:
                self.message(record)
        elif isinstance(record, DataEnd):
            self.in_data = False
        elif isinstance(record, Statistics):
            rec.statistics = record

    def message(self, record: Message) -> None:
        rec = self.rec
        channel = rec.channels.get(record.channel_id)
        if channel is None:
            raise RecordingError(f"{rec.path}: message on channel {record.channel_id}, which was never declared")
        channel.messages += 1
        prefix = rec.prefix
        key, payload, invalid = channel.topic, record.data, None
        if channel.schema_name == INVALID_SCHEMA_NAME:
            try:
                wrapped = json.loads(record.data)
                key, payload = wrapped["key"], base64.b64decode(wrapped["payload_base64"])
                invalid = (wrapped["code"], wrapped["reason"])
            except (ValueError, KeyError, TypeError):
                invalid = ("invalid", "unreadable invalid-payload record")
        raw = self.raw_channels[record.channel_id]
        kind = raw.metadata.get("kind") or None
        if invalid is not None or kind is None:
            kind = _kind_of(key)
        rec.messages.append(RecordedMessage(key, _relative(key, prefix), kind, payload, record.log_time,
                                            record.publish_time, record.sequence, invalid))


def _relative(key: str, prefix: str) -> str:
    return key[len(prefix) + 1:] if prefix and key.startswith(prefix + "/") else key


def _kind_of(key: str) -> str | None:
    try:
        return parse_key(key).kind
    except MessageError:
        return None


def _why(exc: Exception) -> str:
    text = str(exc).strip()
    name = type(exc).__name__
    if name == "EndOfFile" or not text:
        return "the last record is incomplete" if name == "EndOfFile" else name
    return f"{name}: {text.splitlines()[0][:120]}"


def _check_version(path: str, value: str | None) -> None:
    try:
        version = int(value) if value is not None else None
    except ValueError:
        raise RecordingError(f"{path}: schema_version {value!r} in its metadata is not a number") from None
    if version is not None and version > SCHEMA_VERSION:
        raise RecordingError(f"{path}: recorded with message schema version {version}, newer than this dmosim's "
                             f"{SCHEMA_VERSION}; read it with a newer dmosim")


def _check_schema_version(path: str, schema: Schema) -> None:
    if schema.encoding != SCHEMA_ENCODING:
        return
    try:
        found = _SCHEMA_ID.match(str(json.loads(schema.data).get("$id", "")))
    except (ValueError, AttributeError):
        return
    if found:
        _check_version(path, found.group(1))


# --- comparing --------------------------------------------------------------------------------------------------

_TIMESTAMPS = ("sent_at", "received_at")


def content_signature(rec: Recording) -> dict[str, collections.Counter[str]]:
    """What a recording says, apart from timestamps: per key relative to the run prefix, the multiset of its
    payloads with ``sent_at`` (and a rejection's ``received_at``) removed, as canonical JSON. Two runs of the same
    configuration and seed give equal signatures; run ids and clocks differ, contents do not."""
    out: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for m in rec.messages:
        try:
            data = json.loads(m.payload)
        except (ValueError, RecursionError):
            out[m.relative_key][base64.b64encode(m.payload).decode()] += 1
            continue
        if isinstance(data, dict):
            for name in _TIMESTAMPS:
                data.pop(name, None)
        out[m.relative_key][json.dumps(data, sort_keys=True)] += 1
    return dict(out)


__all__ = ["ANY_SCHEMA", "CHUNK_MESSAGES", "FLUSH_INTERVAL_S", "INVALID_KEY", "INVALID_SCHEMA", "MESSAGE_ENCODING",
           "METADATA_NAME", "SCHEMA_ENCODING", "ChannelInfo", "RecordedMessage", "Recorder", "Recording",
           "RecordingError", "RecordingWriter", "content_signature", "read_recording", "versions"]
