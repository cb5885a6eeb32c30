"""Whether a recording's bytes are what its records declare, checked before anything is kept: a chunk decompressed
within its caps and against its CRC, the records inside it, an attachment's CRC, the summary section's CRC, and the
reader's budget of bytes a file may expand to (docs/recording.md, "Reading is bounded and checked")."""

from __future__ import annotations

import io
import os
import struct
import zlib
from typing import Iterator

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Footer, Message, Schema

from .layout import MAX_CHUNK_BYTES, MAX_MESSAGE_BYTES, READ_BUDGET_FLOOR_BYTES, READ_BUDGET_RATIO

MESSAGE_HEADER_BYTES = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time: a Message record before its data
FOOTER_CRC_SPAN = 1 + 8 + 8 + 8        # the footer's opcode, length, summary_start and summary_offset_start


class Refused(ValueError):
    """A record the reader refuses: ``str(err)`` is one line naming the record and what is wrong with it."""


class Budget:
    """What reading one file may hold: the decompressed size of its chunks, its messages' data outside chunks and
    ``MESSAGE_COST_BYTES`` per message, at most ``READ_BUDGET_RATIO`` times the file's size or
    ``READ_BUDGET_FLOOR_BYTES``, whichever is more."""

    def __init__(self, file_size: int):
        self.limit = max(READ_BUDGET_FLOOR_BYTES, READ_BUDGET_RATIO * file_size)
        self.file_size = file_size
        self.held = 0

    def charge(self, n: int, what: str) -> None:
        self.held += n
        if self.held > self.limit:
            raise Refused(f"{what} takes what the file expands to past {self.limit:,} bytes, the cap for a "
                          f"{self.file_size:,}-byte file ({READ_BUDGET_RATIO} x its size, at least "
                          f"{READ_BUDGET_FLOOR_BYTES >> 20} MiB)")


def chunk_data(chunk: Chunk, what: str, budget: Budget) -> bytes:
    """The chunk's records, decompressed: refused if it declares more than ``MAX_CHUNK_BYTES`` or than is left of
    the budget, decompresses to any other size than it declares (checked while decompressing: never more than
    declared is produced), cannot be decompressed, or fails its CRC (zero: not computed, not checked)."""
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise Refused(f"{what} declares {size:,} bytes uncompressed, over the {MAX_CHUNK_BYTES:,}-byte cap on a chunk")
    budget.charge(size, what)
    try:
        if chunk.compression == "zstd":
            data = _zstd(chunk.data, size)
        elif chunk.compression == "lz4":
            data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
        elif chunk.compression == "":
            data = chunk.data
        else:
            raise Refused(f"{what}: unknown compression {chunk.compression[:40]!r}")
    except (zstandard.ZstdError, RuntimeError, ValueError) as exc:
        if isinstance(exc, Refused):
            raise
        raise Refused(f"{what}: cannot decompress its {chunk.compression}: {str(exc).splitlines()[0][:120]}") from None
    if len(data) != size:
        raise Refused(f"{what} decompresses to {'more' if len(data) > size else len(data)} bytes, not the {size:,} "
                      "it declares")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise Refused(f"{what}: CRC mismatch")
    return bytes(data)


def _zstd(compressed: bytes, size: int) -> bytearray:
    """At most ``size`` + 1 bytes of the zstd frames in ``compressed``; a window larger than a chunk may be is
    refused by the decompressor, so it never allocates more than the cap either."""
    out = bytearray(size + 1)
    view = memoryview(out)
    got = 0
    dctx = zstandard.ZstdDecompressor(max_window_size=1 << (MAX_CHUNK_BYTES - 1).bit_length())
    with dctx.stream_reader(compressed, read_across_frames=True) as reader:
        while got <= size:
            n = reader.readinto(view[got:])
            if not n:
                break
            got += n
    view.release()
    del out[got:]
    return out


def chunk_records(data: bytes, what: str) -> Iterator[Schema | Channel | Message]:
    """The schemas, channels and messages of a decompressed chunk, one at a time (a chunk of many tiny messages is
    never a list of all of them); a message longer than ``MAX_MESSAGE_BYTES``, or a record cut short inside the
    chunk, is refused."""
    stream = ReadDataStream(io.BytesIO(data))
    end = len(data)
    while stream.count < end:
        at = stream.count
        try:
            opcode, length = stream.read1(), stream.read8()
        except Exception as exc:  # struct.error, or mcap's EndOfFile
            raise Refused(f"{what}: a record cut short at byte {at} of its contents ({type(exc).__name__})") from None
        if length > end - stream.count:
            raise Refused(f"{what}: the record at byte {at} of its contents is longer than the chunk")
        if opcode == Opcode.MESSAGE and length - MESSAGE_HEADER_BYTES > MAX_MESSAGE_BYTES:
            raise Refused(f"{what}: a message of {length - MESSAGE_HEADER_BYTES:,} bytes, over the "
                          f"{MAX_MESSAGE_BYTES:,}-byte cap on a message")
        start = stream.count
        try:
            record = (Message.read(stream, length) if opcode == Opcode.MESSAGE else
                      Channel.read(stream) if opcode == Opcode.CHANNEL else
                      Schema.read(stream) if opcode == Opcode.SCHEMA else None)
        except Exception as exc:  # a field past the record's end, a name that is not UTF-8...
            raise Refused(f"{what}: unreadable record at byte {at} of its contents ({type(exc).__name__})") from None
        if stream.count - start > length:
            raise Refused(f"{what}: the record at byte {at} of its contents overruns its length")
        if stream.count - start < length:
            stream.read(length - (stream.count - start))  # unknown records and padding
        if record is not None:
            yield record


def check_message(message: Message, what: str) -> None:
    """A message outside any chunk: the same cap as inside one."""
    if len(message.data) > MAX_MESSAGE_BYTES:
        raise Refused(f"{what}: a message of {len(message.data):,} bytes, over the {MAX_MESSAGE_BYTES:,}-byte cap on "
                      "a message")


def check_attachment(fd: int, attachment: Attachment, start: int) -> None:
    """The attachment record that starts at byte ``start`` of the file matches its stored CRC (of every field
    before it); zero means not computed."""
    name, media_type = attachment.name.encode(), attachment.media_type.encode()
    head = struct.pack("<QQ", attachment.log_time, attachment.create_time)
    head += struct.pack("<I", len(name)) + name + struct.pack("<I", len(media_type)) + media_type
    head += struct.pack("<Q", len(attachment.data))
    stored = os.pread(fd, 4, start + 1 + 8 + len(head) + len(attachment.data))
    if len(stored) != 4:
        raise Refused(f"attachment {attachment.name}: its CRC is cut off")
    expected = struct.unpack("<I", stored)[0]
    if expected and zlib.crc32(attachment.data, zlib.crc32(head)) != expected:
        raise Refused(f"attachment {attachment.name}: CRC mismatch")


def check_summary(fd: int, footer: Footer, footer_start: int) -> None:
    """The footer's summary CRC: of every byte from the summary section's start (the footer's own, if there is no
    summary) through the footer's summary_offset_start; zero means not computed."""
    if not footer.summary_crc:
        return
    start = footer.summary_start or footer_start
    if start > footer_start:
        raise Refused(f"footer: its summary_start {start:,} is past the footer (byte {footer_start:,})")
    crc, at, end = 0, start, footer_start + FOOTER_CRC_SPAN
    while at < end:
        block = os.pread(fd, min(1 << 20, end - at), at)
        if not block:
            break
        crc, at = zlib.crc32(block, crc), at + len(block)
    if crc != footer.summary_crc:
        raise Refused("summary section (footer): CRC mismatch")
