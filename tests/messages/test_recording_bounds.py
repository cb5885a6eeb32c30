"""Reading a recording is bounded and checked (messages/recording/integrity.py, docs/recording.md "Reading is bounded
and checked"): small hostile files that would expand to gigabytes are refused in one line, and within a small peak
memory, by every verb that reads them; every CRC the format carries is checked.

The hostile files are built here record by record, their chunks compressed from a stream of blank blocks, so that
none of them is ever whole in this process's memory either.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import lz4.frame
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Schema
from mcap.writer import CompressionType, Writer

from dmosim.bench.recording import synthetic_day
from dmosim.cli import main
from messages import MAX_PAYLOAD_BYTES, MeterReport, encode
from messages.keys import new_run_id
from messages.recording import RecordingError, RecordingWriter, read_recording
from messages.recording.layout import (KEPT_INVALID_BYTES, MAGIC, MAX_CHUNK_BYTES, MAX_MESSAGE_BYTES,
                                       MESSAGE_COST_BYTES, READ_BUDGET_FLOOR_BYTES, READ_BUDGET_RATIO)

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
MIB = 1 << 20
PEAK_MIB = 300
BLANK = bytes(MIB)
TOPIC = "dmosim/hostile-run/dmo/award/mg1"


def message_head(data_len: int) -> bytes:
    """A Message record inside a chunk up to its data: opcode, length, channel 1, sequence, log and publish time."""
    return struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + data_len, 1, 0, 1_700_000_000, 1_700_000_000)


def blank_chunk(messages: int, data_len: int, declared: int | None = None) -> Chunk:
    """A zstd chunk of ``messages`` blank messages of ``data_len`` bytes each, compressed from a stream of blocks of
    at most 1 MiB; ``declared`` is the uncompressed size it claims (default: the true one)."""
    compressor = zstandard.ZstdCompressor().compressobj()
    parts, crc, size = [], 0, 0

    def feed(block: bytes) -> None:
        nonlocal crc, size
        parts.append(compressor.compress(block))
        crc, size = zlib.crc32(block, crc), size + len(block)

    head = message_head(data_len)
    if data_len == 0:  # many tiny messages: a block of them at a time
        per_block = MIB // len(head)
        for start in range(0, messages, per_block):
            feed(head * min(per_block, messages - start))
    for _ in range(messages if data_len else 0):
        feed(head)
        left = data_len
        while left:
            feed(BLANK[:min(left, MIB)])
            left -= min(left, MIB)
    parts.append(compressor.flush())
    return Chunk(message_start_time=0, message_end_time=0, uncompressed_size=size if declared is None else declared,
                 uncompressed_crc=crc, compression="zstd", data=b"".join(parts))


def hostile_file(path: Path, chunks: list[Chunk]) -> Path:
    """Header, a schema and a channel, the chunks, DataEnd, an empty summary and the footer: a well-formed MCAP
    file every other reader opens."""
    builder = RecordBuilder()
    Header(profile="", library="hostile").write(builder)
    Schema(id=1, name="dmosim.award", encoding="jsonschema", data=b"{}").write(builder)
    Channel(id=1, topic=TOPIC, message_encoding="json", schema_id=1, metadata={"kind": "award"}).write(builder)
    for chunk in chunks:
        chunk.write(builder)
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    path.write_bytes(MAGIC + builder.end() + MAGIC)
    return path


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> dict[str, Path]:
    """The reviewer's file (one chunk of 12 x 64 MiB blank messages), the same chunk declaring 1 MiB (so only the
    check while decompressing stops it), and 64 chunks each exactly at the cap (together 1 GiB)."""
    where = tmp_path_factory.mktemp("hostile")
    big = blank_chunk(12, 64 * MIB)
    lying = dataclasses.replace(big, uncompressed_size=MIB)
    per = (MAX_CHUNK_BYTES - 4 * 31) // 4  # each message record is 31 bytes before its data
    at_cap = blank_chunk(4, per)
    assert at_cap.uncompressed_size == MAX_CHUNK_BYTES
    return {"blank-12x64MiB": hostile_file(where / "blank.mcap", [big]),
            "lying": hostile_file(where / "lying.mcap", [lying]),
            "chunks-at-cap": hostile_file(where / "at-cap.mcap", [at_cap] * 64)}


# The verb is started by a small launcher, not by this process: Linux counts the memory of the process a child was
# forked from in the child's peak (ru_maxrss survives exec), so a verb started by a large test worker would show the
# worker's peak. The launcher starts fresh, so its child's peak is the verb's own.
LAUNCHER = """
import os, subprocess, sys
child = subprocess.Popen(sys.argv[2:], stdout=open(sys.argv[1] + "/out", "wb"), stderr=open(sys.argv[1] + "/err", "wb"))
_, status, usage = os.wait4(child.pid, 0)
print(os.waitstatus_to_exitcode(status), usage.ru_maxrss)
"""


def run_measured(args: list[str], cwd: Path) -> tuple[int, str, float]:
    """A dmosim verb as a real process: its exit code, stderr and peak resident memory (MiB, from wait4)."""
    launched = subprocess.run([sys.executable, "-c", LAUNCHER, str(cwd), sys.executable, "-m", "dmosim", *args],
                              cwd=cwd, env=ENV, capture_output=True, text=True, check=True)
    code, peak_kib = map(int, launched.stdout.split())
    return code, (cwd / "err").read_text(), peak_kib / 1024


def test_the_hostile_files_are_small(hostile):
    sizes = {name: path.stat().st_size for name, path in hostile.items()}
    assert sizes["blank-12x64MiB"] < 64 * 1024 and sizes["chunks-at-cap"] < 256 * 1024, sizes


def hostile_runs(hostile: dict[str, Path], verb: str, tmp_path: Path):
    """(name, path, the command line) of ``verb`` on each hostile file that tells something of it."""
    for name, path in hostile.items():
        if name == "lying" and verb != "info":
            continue  # what it takes is that of the first; info alone shows it is caught while decompressing
        yield name, path, [verb, str(path), *{"export": ["--out", str(tmp_path / "tables")],
                                        "plot": ["--out", str(tmp_path / "day.png")]}.get(verb, [])]


@pytest.mark.parametrize("verb", ["info", "cat", "settle", "export", "plot"])
def test_every_verb_refuses_a_hostile_file_in_one_line(hostile, verb, tmp_path, cli):
    for name, _, args in hostile_runs(hostile, verb, tmp_path):
        out = cli(*args)
        assert out.returncode == 2 and out.stderr.count("\n") == 1, (name, out)
        assert out.stderr.startswith("error: ") and "chunk at byte" in out.stderr, (name, out.stderr)


@pytest.mark.slow  # a peak of its own is a process's
@pytest.mark.parametrize("verb", ["info", "cat", "settle", "export", "plot"])
def test_every_verb_refuses_a_hostile_file_in_one_line_within_a_small_peak(hostile, verb, tmp_path):
    for name, path, args in hostile_runs(hostile, verb, tmp_path):
        code, err, peak = run_measured(args, tmp_path)
        assert code == 2 and err.count("\n") == 1 and err.startswith("error: "), (name, code, err[-2000:])
        assert "chunk at byte" in err and "Traceback" not in err, (name, err)
        assert peak < PEAK_MIB, f"{verb} {name}: peak {peak:.0f} MiB"
        print(f"\n{verb} {name} ({path.stat().st_size:,} bytes): exit {code}, peak {peak:.0f} MiB: {err.strip()}")


@pytest.fixture(scope="module")
def flood(tmp_path_factory) -> Path:
    """A recorded day followed by copies of one valid meter report (60 sub-periods) up to the reader's budget:
    well-formed and small, it reads, and every verb that decodes it holds only what it needs of it."""
    run_id, path = new_run_id(), tmp_path_factory.mktemp("flood") / "flood.mcap"
    report = encode(MeterReport(sender="mg1", market_day="2026-07-01", hour=1, subperiods=60,
                                p_m_mw=tuple(1.25 + i / 64 for i in range(60)), deviation_mw=(0.25,) * 60))
    copies = (READ_BUDGET_FLOOR_BYTES - 4 * MIB) // (len(report) + MESSAGE_COST_BYTES)
    with RecordingWriter(path, run_id) as writer:
        writer.start({"market_day": "2026-07-01", "agents": "mg1"})
        day = synthetic_day(run_id, 1, 60)
        for i, (key, payload) in enumerate(day):
            writer.write(key, payload, 1_700_000_000_000_000_000 + i)
        for i in range(copies):  # after the day's own reports: the DMO would have refused every one
            writer.write(f"dmosim/{run_id}/agent/mg1/meter", report, 1_800_000_000_000_000_000 + i)
    assert len(read_recording(path).messages) == len(day) + copies and path.stat().st_size < 2 * MIB
    return path


@pytest.mark.slow
def test_every_verb_reads_a_flood_of_valid_messages_within_a_small_peak(flood, tmp_path):
    for verb, more in (("info", []), ("cat", []), ("settle", []), ("export", ["--out", str(tmp_path / "tables")]),
                       ("plot", ["--out", str(tmp_path / "day.png")])):
        code, err, peak = run_measured([verb, str(flood), *more], tmp_path)
        assert code == 0, (verb, err[-2000:])
        assert peak < PEAK_MIB, f"{verb}: peak {peak:.0f} MiB"
        print(f"\n{verb} flood ({flood.stat().st_size:,} bytes): exit {code}, peak {peak:.0f} MiB")


def test_a_chunk_over_the_cap_is_refused_before_it_is_decompressed(hostile):
    with pytest.raises(RecordingError) as err:
        read_recording(hostile["blank-12x64MiB"])
    assert f"declares {12 * (64 * MIB + 31):,} bytes uncompressed, over the {MAX_CHUNK_BYTES:,}-byte cap" in str(err.value)


def test_a_chunk_that_expands_past_what_it_declares_is_stopped_while_decompressing(hostile):
    with pytest.raises(RecordingError, match=f"decompresses to more bytes, not the {MIB:,} it declares"):
        read_recording(hostile["lying"])


def test_chunks_at_the_cap_are_refused_once_the_file_has_expanded_past_its_budget(hostile):
    with pytest.raises(RecordingError) as err:
        read_recording(hostile["chunks-at-cap"])
    text = str(err.value)
    assert text.startswith(f"{hostile['chunks-at-cap']}: chunk at byte ") and "\n" not in text
    assert "takes what the file expands to past" in text and f"at least {READ_BUDGET_FLOOR_BYTES >> 20} MiB" in text


def test_many_tiny_messages_are_charged_what_holding_them_costs(tmp_path):
    """16 MiB of empty messages is half a million objects: each is charged MESSAGE_COST_BYTES, so a few such
    chunks cannot hold gigabytes of Python objects."""
    tiny = blank_chunk(MAX_CHUNK_BYTES // 31, 0)
    path = hostile_file(tmp_path / "tiny.mcap", [tiny] * 8)
    assert path.stat().st_size < 64 * 1024
    with pytest.raises(RecordingError, match="takes what the file expands to past"):
        read_recording(path)
    assert MESSAGE_COST_BYTES * (MAX_CHUNK_BYTES // 31) > MAX_CHUNK_BYTES  # the cost, not the bytes, runs out


def test_a_message_over_the_cap_is_refused_inside_a_chunk_and_outside(tmp_path):
    inside = hostile_file(tmp_path / "inside.mcap", [blank_chunk(1, MAX_MESSAGE_BYTES + 1)])
    with pytest.raises(RecordingError, match=f"a message of {MAX_MESSAGE_BYTES + 1:,} bytes, over the"):
        read_recording(inside)
    outside = tmp_path / "outside.mcap"
    with open(outside, "wb") as f:
        w = Writer(f, use_chunking=False)
        w.start()
        channel = w.register_channel(TOPIC, "json", w.register_schema("dmosim.award", "jsonschema", b"{}"))
        w.add_message(channel, log_time=1, data=bytes(MAX_MESSAGE_BYTES + 1), publish_time=1)
        w.finish()
    with pytest.raises(RecordingError, match=r"message at byte [\d,]+: a message of [\d,]+ bytes, over the"):
        read_recording(outside)


# --- CRCs ---------------------------------------------------------------------------------------------------------

@pytest.fixture
def day(tmp_path) -> Path:
    """A small day as the recorder writes it, with an experiment attachment."""
    run_id, path = new_run_id(), tmp_path / "day.mcap"
    with RecordingWriter(path, run_id) as writer:
        writer.start({"market_day": "2026-07-01"}, [("experiment.toml", "application/toml",
                                                     b"[schedule]\nscenarios = 2\n")])
        for i, (key, payload) in enumerate(synthetic_day(run_id, 1, 1)):
            writer.write(key, payload, 1_700_000_000_000_000_000 + i)
    assert read_recording(path).complete
    return path


def edited(path: Path, old: bytes, new: bytes, last: bool = False) -> Path:
    """The file with one occurrence of ``old`` (the first, or the last) replaced by ``new`` of the same length."""
    data = path.read_bytes()
    at = data.rindex(old) if last else data.index(old)
    out = path.with_name("edited.mcap")
    out.write_bytes(data[:at] + new + data[at + len(old):])
    return out


def test_an_edited_attachment_fails_its_crc(day, capsys):
    path = edited(day, b"scenarios = 2", b"scenarios = 3")
    with pytest.raises(RecordingError) as err:
        read_recording(path)
    assert str(err.value) == f"{path}: attachment experiment.toml: CRC mismatch"
    assert main(["run", "--from", str(day), "--check"]) == 0  # the same recording, unedited, runs again
    capsys.readouterr()
    assert main(["run", "--from", str(path), "--check"]) == 2
    assert capsys.readouterr().err == f"error: {path}: attachment experiment.toml: CRC mismatch\n"


def test_an_edited_summary_fails_the_footers_crc(day):
    topic = next(iter(read_recording(day).channels.values())).topic.encode()
    with pytest.raises(RecordingError, match="summary section \\(footer\\): CRC mismatch$"):
        read_recording(edited(day, topic, topic.upper(), last=True))  # the summary repeats every channel


def test_an_edited_chunk_fails_its_crc(tmp_path):
    chunk = blank_chunk(2, 100)
    with pytest.raises(RecordingError, match="chunk at byte 157: CRC mismatch$"):
        read_recording(hostile_file(tmp_path / "crc.mcap", [dataclasses.replace(
            chunk, uncompressed_crc=chunk.uncompressed_crc ^ 1)]))


def test_an_edited_data_section_fails_the_data_end_crc(tmp_path):
    path = tmp_path / "data-crc.mcap"
    with open(path, "wb") as f:
        w = Writer(f, enable_data_crcs=True)
        w.start()
        w.add_metadata("dmosim", {"run_id": "abc"})
        w.finish()
    assert read_recording(path).complete
    with pytest.raises(RecordingError, match="data section \\(DataEnd at byte [\\d,]+\\): CRC mismatch$"):
        read_recording(edited(path, b"abc", b"abd"))


def test_a_zero_crc_means_not_computed_and_is_not_checked(tmp_path):
    path = tmp_path / "no-crcs.mcap"
    with open(path, "wb") as f:
        w = Writer(f, enable_crcs=False)
        w.start()
        w.add_attachment(create_time=0, log_time=0, name="experiment.toml", media_type="application/toml",
                         data=b"scenarios = 2\n")
        channel = w.register_channel(TOPIC, "json", w.register_schema("dmosim.award", "jsonschema", b"{}"))
        w.add_message(channel, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    data = path.read_bytes()  # mcap computes an attachment's CRC always: zero it, as a writer that does not would
    at = data.index(b"scenarios = 2\n")
    rec = read_recording(edited(path, data[at:at + 18], b"scenarios = 3\n" + bytes(4)))
    assert rec.complete and rec.attachments[0].data == b"scenarios = 3\n" and len(rec.messages) == 1


def test_a_cut_file_still_reads_what_precedes_the_cut(day):
    data = day.read_bytes()
    for keep in (len(data) - 40, len(data) // 2):
        cut = day.with_name("cut.mcap")
        cut.write_bytes(data[:keep])
        rec = read_recording(cut)
        assert not rec.complete and "file cut after" in rec.cut_note


@pytest.mark.slow
def test_what_the_writer_writes_is_far_inside_the_caps(tmp_path):
    """A day of 100 agents at 60 sub-periods, as the recorder writes it: its largest chunk and its expansion,
    charged as the reader charges them, leave the caps a wide margin."""
    run_id, path = new_run_id(), tmp_path / "big.mcap"
    mix = synthetic_day(run_id, 100, 60)
    with RecordingWriter(path, run_id) as writer:
        writer.start()
        for i, (key, payload) in enumerate(mix):
            writer.write(key, payload, 1_700_000_000_000_000_000 + i)
    rec = read_recording(path)
    assert rec.complete and len(rec.messages) == len(mix)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    charged = sum(c.uncompressed_size for c in chunks) + MESSAGE_COST_BYTES * len(mix)
    largest = max(c.uncompressed_size for c in chunks)
    print(f"\n{len(mix)} messages: {path.stat().st_size:,} bytes, {len(chunks)} chunks, largest {largest:,} bytes; "
          f"charged {charged:,} bytes = {charged / path.stat().st_size:.1f} x the file")
    assert largest < MAX_CHUNK_BYTES / 8 and charged < READ_BUDGET_RATIO / 4 * path.stat().st_size


def test_the_writer_keeps_an_invalid_payload_to_its_first_bytes_and_none_past_the_files_share(tmp_path,
                                                                                               monkeypatch):
    """Whatever a peer sends, what the recorder writes of an invalid payload is bounded: whole up to
    KEPT_INVALID_BYTES, else its first KEPT_INVALID_BYTES, and nothing once the file holds KEPT_INVALID_TOTAL bytes
    of them; its size and SHA-256 are kept always (60 refused payloads of 1 MiB once made a 174 KB file that no
    verb could read)."""
    monkeypatch.setattr("messages.recording.writer.KEPT_INVALID_TOTAL", 3 * KEPT_INVALID_BYTES)
    run_id, path = new_run_id(), tmp_path / "flood.mcap"
    huge = b'{"kind":"meter_report","pad":"' + b"x" * (3 * MAX_MESSAGE_BYTES) + b'"}'
    small = b'{"kind":"meter_report"}'
    sent = [(f"dmosim/{run_id}/agent/mg1/meter", huge), (f"dmosim/{run_id}/somewhere/else", huge),
            (f"dmosim/{run_id}/agent/mg1/meter", small), (f"dmosim/{run_id}/agent/mg1/meter", huge),
            (f"dmosim/{run_id}/agent/mg1/meter", small)]
    with RecordingWriter(path, run_id) as writer:
        writer.start()
        for at, (key, payload) in enumerate(sent):
            writer.write(key, payload, at + 1)
    rec = read_recording(path)
    assert [m.invalid[0] for m in rec.messages] == ["oversize", "oversize", "invalid", "oversize", "invalid"]
    kept = [huge[:KEPT_INVALID_BYTES], huge[:KEPT_INVALID_BYTES], small, huge[:KEPT_INVALID_BYTES - len(small)], b""]
    assert [m.payload for m in rec.messages] == kept
    with open(path, "rb") as f:
        wrapped = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages()]
    assert [(w["payload_size"], w["payload_sha256"]) for w in wrapped] == [
        (len(payload), hashlib.sha256(payload).hexdigest()) for _, payload in sent]

def test_the_caps_are_documented_as_they_are():
    doc = (ROOT / "docs" / "recording.md").read_text()
    for said in (f"at most {MAX_CHUNK_BYTES >> 20} MiB (`MAX_CHUNK_BYTES`)",
                 f"at most {MAX_MESSAGE_BYTES >> 20} MiB (`MAX_MESSAGE_BYTES`)",
                 f"plus {MESSAGE_COST_BYTES} bytes per message (`MESSAGE_COST_BYTES`",
                 f"at most {READ_BUDGET_RATIO} times the file's size (`READ_BUDGET_RATIO`)",
                 f"or {READ_BUDGET_FLOOR_BYTES >> 20} MiB (`READ_BUDGET_FLOOR_BYTES`)"):
        assert said in doc, said


def test_an_lz4_chunk_is_read_within_the_same_caps(tmp_path):
    """Other writers compress with lz4: read alike, and stopped alike when it expands past what it declares."""
    path = tmp_path / "lz4.mcap"
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.LZ4)
        w.start()
        channel = w.register_channel(TOPIC, "json", w.register_schema("dmosim.award", "jsonschema", b"{}"))
        for i in range(3):
            w.add_message(channel, log_time=i, data=bytes(100_000), publish_time=i)
        w.finish()
    rec = read_recording(path)
    assert rec.complete and rec.compression == {"lz4"} and [len(m.payload) for m in rec.messages] == [100_000] * 3
    chunk = Chunk(message_start_time=0, message_end_time=0, uncompressed_size=1000, uncompressed_crc=0,
                  compression="lz4", data=lz4.frame.compress(message_head(MIB) + BLANK))
    with pytest.raises(RecordingError, match="decompresses to more bytes, not the 1,000 it declares"):
        read_recording(hostile_file(tmp_path / "lying-lz4.mcap", [chunk]))
