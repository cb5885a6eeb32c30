"""Read a recording front to back, surviving a cut or torn end (every complete record before the damage is kept) and
refusing a file whose records fail their checks (integrity.py): a CRC, a cap on what it may expand to."""

from __future__ import annotations

import base64
import json
import os
from dataclasses import dataclass, field
from typing import Iterable, Iterator

from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import CRCValidationError, StreamReader

from ..codec import MessageError, decode
from ..keys import ROOT, parse_key, relative_key
from ..schemas import SCHEMA_VERSION
from .integrity import Budget, Refused, check_attachment, check_message, check_summary, chunk_data, chunk_records
from .layout import INVALID_SCHEMA_NAME, MAGIC, MESSAGE_COST_BYTES, METADATA_NAME, SCHEMA_ENCODING, SCHEMA_ID


class RecordingError(ValueError):
    """A file that cannot be read as a recording: ``str(err)`` is one line naming the file and the problem."""


@dataclass(frozen=True, slots=True)
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
    _run_token: tuple[str | None] | None = field(default=None, init=False, repr=False, compare=False)
    _receipted: tuple[frozenset[tuple[str, str]] | None] | None = field(default=None, init=False, repr=False,
                                                                      compare=False)

    @property
    def run_token(self) -> str | None:
        """The run's token (docs/protocol.md, "The envelope"): the one the DMO's first recorded clock carries, None
        if no clock is recorded. A message that carries another was not of the run (a replay of another run's, or
        a forgery): the readers of a recording skip it, as the run's processes did."""
        if self._run_token is None:
            clocks = (m for m in self.in_log_order() if m.kind == "clock" and m.invalid is None)
            self._run_token = (next((msg.run for msg in map(_clock, clocks) if msg is not None), None),)
        return self._run_token[0]

    @property
    def receipted(self) -> frozenset[tuple[str, str]] | None:
        """(agent, SHA-256 of the payload as received) of every payload the DMO's recorded receipts say it accepted;
        None if the recording holds no receipt (one of before protocol 4). Read once: every day and kind asks."""
        if self._receipted is None:
            accepted, any_receipt = set(), False
            for _, receipt in self.decoded("receipt"):
                any_receipt = True
                if receipt.accepted:
                    accepted.add((receipt.agent, receipt.payload_sha256))
            self._receipted = (frozenset(accepted) if any_receipt else None,)
        return self._receipted[0]

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

    def decoded(self, kind: str) -> Iterator[tuple[RecordedMessage, object]]:
        """The valid messages of one kind with their decoded form, in log order, one at a time: decoded, a day's
        messages take several times the memory of their bytes, so none is held longer than its caller needs."""
        token = self.run_token
        for m in sorted((m for m in self.messages if m.kind == kind and m.invalid is None), key=lambda m: m.log_time):
            try:
                msg = decode(m.payload, expected_kind=kind)
            except MessageError:
                continue
            if token is None or msg.run == token:
                yield m, msg


def _clock(m: RecordedMessage):
    """A recorded clock, decoded, if the DMO sent it (None otherwise)."""
    try:
        msg = decode(m.payload, expected_kind="clock")
    except MessageError:
        return None
    return msg if msg.sender == "dmo" and m.relative_key == "dmo/clock" else None


def _prefix_of(topics: Iterable[str]) -> str:
    for topic in topics:
        parts = topic.split("/")
        if len(parts) > 2 and parts[0] == ROOT:
            return f"{parts[0]}/{parts[1]}"
    return ""


def read_recording(path: str | os.PathLike) -> Recording:
    """Read a recording front to back, tolerating a cut or torn end: whatever complete records precede the damage
    are returned, with ``complete`` False. Raises RecordingError (one line) for a file that is not MCAP, is cut
    before its header, was written with a newer message schema version than this dmosim reads, fails a CRC, or
    declares or expands to more than the reader's caps (docs/recording.md, "Reading is bounded and checked")."""
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
        try:
            _Scan(rec, f).run()
        except Refused as err:
            raise RecordingError(f"{name}: {err}") from None
    if not rec.library and not rec.profile and not rec.messages and rec.bytes_read <= len(MAGIC):
        raise RecordingError(f"{name}: file cut after {size} bytes, before its MCAP header was complete")
    prefix = rec.prefix
    for channel in rec.channels.values():
        channel.relative_key = relative_key(channel.topic, prefix)
    return rec


class _Scan:
    """Fills a Recording from the records of a file, stopping at the first record that cannot be read whole (a cut
    end) and refusing, with ``Refused``, a whole record that fails a check of integrity.py."""

    def __init__(self, rec: Recording, f):
        self.rec, self.f = rec, f
        self.raw_channels: dict[int, Channel] = {}
        self.in_data = True
        self.budget = Budget(rec.size)
        self.footer: tuple[Footer, int] | None = None

    def run(self) -> None:
        rec, f = self.rec, self.f
        records = StreamReader(f, emit_chunks=True, validate_crcs=True, record_size_limit=max(rec.size, 1)).records
        start = len(MAGIC)
        while True:
            try:
                record = next(records)
            except StopIteration:
                if self.footer is not None:
                    check_summary(f.fileno(), *self.footer)
                rec.complete = True
                rec.bytes_read = rec.size
                return
            except CRCValidationError:  # the only one a stream raises: the data section's, at DataEnd
                raise Refused(f"data section (DataEnd at byte {start:,}): CRC mismatch") from None
            except Exception as exc:  # EndOfFile, struct.error, InvalidMagic, a record too long for the file...
                rec.cut_reason = _why(exc)
                return
            try:
                self.record(record, start)
            except (RecordingError, Refused):
                raise
            except Exception as exc:  # a record mcap parsed that makes no sense as a whole (a bad schema version...)
                rec.cut_reason = _why(exc)
                return
            start = f.tell()
            if not isinstance(record, Footer):
                rec.bytes_read = start

    def record(self, record, start: int | None) -> None:
        """File one record; ``start`` is where it begins in the file (None inside a chunk)."""
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
            check_attachment(self.f.fileno(), record, start)
            rec.attachments.append(record)
        elif isinstance(record, Chunk):
            what = f"chunk at byte {start:,}"
            data = chunk_data(record, what, self.budget)  # a damaged chunk is refused here, before any of it is kept
            rec.chunks += 1
            rec.compression.add(record.compression or "none")
            for part in chunk_records(data, what):
                if isinstance(part, Message):
                    self.budget.charge(MESSAGE_COST_BYTES, what)
                self.record(part, None)
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
            if start is not None:  # outside any chunk (a chunk's were charged with it)
                what = f"message at byte {start:,}"
                check_message(record, what)
                self.budget.charge(len(record.data) + MESSAGE_COST_BYTES, what)
            if self.in_data:
                self.message(record)
        elif isinstance(record, DataEnd):
            self.in_data = False
        elif isinstance(record, Statistics):
            rec.statistics = record
        elif isinstance(record, Footer):
            self.footer = (record, start)

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
        rec.messages.append(RecordedMessage(key, relative_key(key, prefix), kind, payload, record.log_time,
                                            record.publish_time, record.sequence, invalid))


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
        found = SCHEMA_ID.match(str(json.loads(schema.data).get("$id", "")))
    except (ValueError, AttributeError):
        return
    if found:
        _check_version(path, found.group(1))
