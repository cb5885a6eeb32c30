"""Recording, inspecting, replaying and re-settling market days: MCAP files as any reader sees them, real processes.

One tiny recorded day (``dmosim run``, 2 agents, 1 sub-period) is shared by the module's slow tests; the determinism
test runs a second one. Every process is started through ``Roles`` or ``subprocess.run`` with a timeout, on free
ports and fresh run ids, so nothing outlives a failing test. What needs neither a day nor a process (the writer, the
recorder's loop and bookkeeping, the commands on bad files) runs in this process, in the fast tier.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import datetime
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import jsonschema
import pandas as pd
import pytest
import zenoh
from mcap.reader import make_reader
from mcap.writer import Writer

from dmosim.bench.recording import synthetic_day
from dmosim.launch.processes import Roles, free_port
from messages import SCHEMA_VERSION, decode
from messages.transport import Bus, BusConfig
from messages.keys import Keys, key_pattern, new_run_id
from messages.recording import INVALID_KEY, RecordingWriter, content_signature, read_recording, select
from messages.recording import writer as writer_module
from messages.recording.recorder import Recorder
from messages.recording.writer import WrittenChunkIndex

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
DAY = "2026-07-01"
FLEET = "".join(f'[[agents]]\nid = "mg{i}"\ncase = "paper"\nscale = 1.0\nshift_hours = 0\nseed = {i}\n\n' for i in (1, 2))
TINY = ["--subperiods", "1", "--scenarios", "1", "--gap", "0.05", "--time-limit", "60", "--seed", "0",
        "--market-day", DAY, "--registration-timeout", "60", "--bid-timeout", "120", "--schedule-timeout", "120",
        "--hour-timeout", "60"]


def dmosim(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dmosim", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, env=ENV)


def argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "dmosim", *args]


def run_day(directory: Path) -> tuple[Path, dict]:
    (directory / "fleet.toml").write_text(FLEET)
    out = dmosim("run", *TINY, "--fleet", str(directory / "fleet.toml"), "--out", str(directory / "run"),
                 "--record", str(directory / "day.mcap"), "--json", timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return directory / "day.mcap", json.loads(out.stdout)


@pytest.fixture(scope="module")
def day(tmp_path_factory) -> tuple[Path, dict]:
    """One recorded day, and the result ``dmosim run --json`` printed for it."""
    return run_day(tmp_path_factory.mktemp("day"))


def one_line_error(out) -> str:
    """The one line a command refused its input with (exit 2), from what it said (``CompletedProcess`` or ``Said``)."""
    assert out.returncode == 2, (out.returncode, out.stdout[-500:], out.stderr[-2000:])
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr, out.stderr
    return out.stderr


# --- the recorded day ------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_dmosim_run_records_every_message_of_the_day(day):
    path, result = day
    assert Path(result["recording"]).samefile(path) and result["recorded"]["complete"]
    rec = read_recording(path)
    assert rec.complete and rec.run_id == result["run_id"] and rec.prefix == f"dmosim/{result['run_id']}"
    expected = {"dmo/clock": 29, "dmo/call_for_bids": 1, "dmo/grid": 24, "dmo/summary": 1}
    for agent in ("mg1", "mg2"):
        expected.update({f"agent/{agent}/register": 1, f"agent/{agent}/bid": 1, f"agent/{agent}/schedule": 1,
                         f"agent/{agent}/meter": 24, f"agent/{agent}/day": 1, f"dmo/award/{agent}": 1,
                         f"dmo/statement/{agent}": 1,
                         f"dmo/receipt/{agent}": 28})  # one per message of the agent, each accepted
    assert distinct_messages(rec) == expected
    receipts = [json.loads(m.payload) for m in rec.messages if m.kind == "receipt"]
    assert all(r["accepted"] for r in receipts)
    assert result["recorded"]["messages"] == len(rec.messages)
    assert all(m.invalid is None for m in rec.messages)
    clock = [decode(m.payload) for m in rec.in_log_order() if m.kind == "clock"]
    assert clock[0].phase == "registration" and clock[-1].phase == "settlement"  # from the very first message
    for m in rec.messages:  # log_time is the receipt, publish_time the sender's own stamp
        assert m.publish_time == json.loads(m.payload)["sent_at"] <= m.log_time
    meta = rec.metadata
    assert meta["schema_version"] == str(SCHEMA_VERSION) and meta["seed"] == "0" and meta["market_day"] == DAY
    assert meta["days"] == "1" and meta["agents"] == "mg1,mg2"
    assert json.loads(meta["config"])["schedule"]["scenarios"] == 1
    assert {"dmosim", "python", "mcap", "eclipse-zenoh"} <= set(json.loads(meta["versions"]))
    assert {a.name for a in rec.attachments} == {"experiment.toml", "paper.toml", "fleet.toml"}
    fleet = tomllib.loads(next(a for a in rec.attachments if a.name == "fleet.toml").data.decode())
    assert [a["id"] for a in fleet["agents"]] == ["mg1", "mg2"]


def distinct_messages(rec) -> collections.Counter:
    """Messages per key, a payload sent again (for want of a receipt) counted once, and so its receipts."""
    seen = {(m.relative_key, json.loads(m.payload)["payload_sha256"] if m.kind == "receipt" else m.payload)
            for m in rec.messages}
    return collections.Counter(key for key, _ in seen)


@pytest.mark.slow
def test_a_plain_mcap_reader_opens_it_and_every_message_fits_its_channel_schema(day):
    path, _ = day
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(read_recording(path).messages)
        assert len(summary.channels) == 20
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert all(c.message_index_offsets for c in summary.chunk_indexes)
        validators = {}
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            assert channel.topic.startswith(f"dmosim/{summary_run_id(reader)}/")
            if schema.id not in validators:
                document = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(document)
                validators[schema.id] = jsonschema.Draft202012Validator(document)
            validators[schema.id].validate(json.loads(message.data))
        assert len(validators) == 12  # one schema per kind
        [meta] = list(reader.iter_metadata())
        assert meta.name == "dmosim" and "config" in meta.metadata
        assert {a.name for a in reader.iter_attachments()} == {"experiment.toml", "paper.toml", "fleet.toml"}


def summary_run_id(reader) -> str:
    return next(reader.iter_metadata()).metadata["run_id"]


@pytest.mark.slow
def test_info_shows_the_run_the_day_the_agents_and_each_channel(day):
    path, result = day
    out = dmosim("info", str(path), "--json")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["complete"] and info["run_id"] == result["run_id"] and info["market_days"] == [DAY]
    assert info["agents"] == ["mg1", "mg2"] and info["seed"] == 0 and info["duration_s"] > 0
    assert info["versions"]["dmosim"] and info["config"]["schedule"]["scenarios"] == 1
    channels = {c["key"]: c for c in info["channels"]}
    recorded = collections.Counter(m.relative_key for m in read_recording(path).messages)  # copies sent again too
    assert channels["agent/mg1/meter"]["messages"] == recorded["agent/mg1/meter"] >= 24
    assert channels["agent/mg1/meter"]["schema"] == "dmosim.meter_report"
    text = dmosim("info", str(path)).stdout
    assert "market day:  2026-07-01" in text and "agents:      mg1, mg2" in text and "complete" in text
    assert re.search(r"dmo/grid\s+24\s+dmosim.grid_state \(jsonschema, json\)", text)


# --- settlement from the recording -----------------------------------------------------------------------------

@pytest.mark.slow
def test_settle_reproduces_every_recorded_statement(day):
    out = dmosim("settle", str(day[0]))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "identical" in out.stdout and "48 hour lines" in out.stdout


def _copy(src: Path, dst: Path, change) -> None:
    """Copy a recording with the plain mcap reader and writer, passing each message's data through change()."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader, writer = make_reader(f), Writer(g)
        writer.start(profile="", library="test tamper")
        summary = reader.get_summary()
        for m in reader.iter_metadata():
            writer.add_metadata(m.name, m.metadata)
        schemas = {i: writer.register_schema(s.name, s.encoding, s.data) for i, s in summary.schemas.items()}
        channels = {i: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id], c.metadata)
                    for i, c in summary.channels.items()}
        for _, channel, message in reader.iter_messages():
            writer.add_message(channels[channel.id], log_time=message.log_time, publish_time=message.publish_time,
                               data=change(channel.topic, message.data))
        writer.finish()


@pytest.mark.slow
def test_settle_lists_a_tampered_statement_line_and_exits_1(day, tmp_path):
    tampered = tmp_path / "tampered.mcap"

    def change(topic, data):
        if not topic.endswith("/dmo/statement/mg2"):
            return data
        st = json.loads(data)  # one more dollar of penalty in hour 7, carried into the totals so that it is valid
        for item in (st["lines"][6], st):
            item["deviation_penalty"] = round(item["deviation_penalty"] + 1.0, 2)
            item["total"] = round(item["total"] + 1.0, 2)
        return json.dumps(st).encode()

    _copy(day[0], tampered, change)
    assert dmosim("settle", str(tampered)).returncode == 1
    out = dmosim("settle", str(tampered), "--json")
    assert out.returncode == 1
    diffs = json.loads(out.stdout)["differences"]
    assert any(d.startswith("mg2 hour 7 deviation_penalty: recorded") for d in diffs)
    assert any(d.startswith("mg2 hour 7 total: recorded") for d in diffs)
    assert any(d.startswith("mg2 total: recorded") for d in diffs) and not any(d.startswith("mg1") for d in diffs)


@pytest.mark.slow
def test_settle_under_another_penalty_rate_prints_the_change_per_agent(day):
    statements = {m.agent: m for _, m in read_recording(day[0]).decoded("settlement_statement")}
    out = dmosim("settle", str(day[0]), "--penalty", "0", "--json")
    assert out.returncode == 0, out.stderr
    rows = {r["agent"]: r for r in json.loads(out.stdout)["rows"]}
    assert set(rows) == {"mg1", "mg2"} and {r["rule"] for r in rows.values()} == {"paper:penalty=0,credit=0"}
    for agent, st in statements.items():
        assert rows[agent]["recorded_total"] == st.total and rows[agent]["total"] == st.energy_charge
        assert rows[agent]["change"] == pytest.approx(-st.deviation_penalty, abs=1e-9)
    doubled = {r["agent"]: r for r in json.loads(dmosim("settle", str(day[0]), "--penalty", "300", "--json").stdout)["rows"]}
    for agent, st in statements.items():  # twice the rate, twice the penalty (each line rounds once: 24 cents)
        assert doubled[agent]["change"] == pytest.approx(st.deviation_penalty, abs=0.24)
    text = dmosim("settle", str(day[0]), "--penalty", "300").stdout
    assert "held fixed" in text and re.search(r"^\S+\s+mg1\s+paper:penalty=300,credit=0\s", text, re.M)


@pytest.mark.slow
def test_settle_compares_rules_on_recordings_and_run_directories_in_one_table(day, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "recording.mcap").write_bytes(day[0].read_bytes())
    table = tmp_path / "rules.csv"
    rules = ["paper", "deadband:band_mw=0.5", "examples/settlement_rule.py:capped_penalty:cap=50"]
    out = dmosim("settle", str(day[0]), str(run_dir), *(a for r in rules for a in ("--rule", r)), "--csv", str(table),
                 "--json")
    assert out.returncode == 0, out.stderr
    rows = pd.read_csv(table)
    assert len(rows) == 2 * 3 * 2 and rows.to_dict("records") == json.loads(out.stdout)["rows"]
    recorded = {m.agent: m.total for _, m in read_recording(day[0]).decoded("settlement_statement")}
    for r in rows.itertuples():
        assert r.recorded_total == recorded[r.agent] and r.total == pytest.approx(r.recorded_total + r.change)
        assert r.total == pytest.approx(r.energy_charge + r.deviation_penalty - r.deviation_credit)
    paper = rows[rows.rule == "paper:penalty=150,credit=0"]
    assert (paper.change == 0).all()  # the recorded day was settled by the paper rule at $150
    capped = rows[rows.rule.str.contains("capped_penalty")]
    assert (capped.deviation_penalty <= 50).all()
    assert one_line_error(dmosim("settle", str(day[0]), "--rule", "deadband:width=1")).startswith(
        "error: --rule: settlement rule deadband has no parameter 'width'")


# --- cut and bad files -----------------------------------------------------------------------------------------

@pytest.mark.slow
def test_info_and_settle_read_a_cut_file_and_say_so(day, tmp_path):
    data = day[0].read_bytes()
    without_end = tmp_path / "no_summary.mcap"  # everything but the footer: all messages, no summary
    without_end.write_bytes(data[:-40])
    messages = len(read_recording(day[0]).messages)
    info = dmosim("info", str(without_end), "--json")
    assert info.returncode == 0, info.stderr
    assert not json.loads(info.stdout)["complete"] and json.loads(info.stdout)["messages"] == messages
    settled = dmosim("settle", str(without_end), "--json")
    assert settled.returncode == 0, settled.stderr
    outcome = json.loads(settled.stdout)
    assert outcome["identical"] and not outcome["complete"] and outcome["lines"] == 48

    with open(day[0], "rb") as f:  # cut in the middle of the middle chunk
        chunks = make_reader(f).get_summary().chunk_indexes
    middle = chunks[len(chunks) // 2]
    half = tmp_path / "half.mcap"
    half.write_bytes(data[: middle.chunk_start_offset + middle.chunk_length // 2])
    text = dmosim("info", str(half))
    assert text.returncode == 0 and "INCOMPLETE: file cut after" in text.stdout
    n = int(re.search(r"file cut after (\d+) messages \((\d+\.\d)% of", text.stdout).group(1))
    assert 0 < n < messages
    # what is cut off depends on where the chunk boundaries fell: the awards (a fast day fits in few chunks) or
    # only the statements; either way the file cannot be settled, and the one line says what is missing
    assert re.search(r": no (awards|settlement statements) recorded", one_line_error(dmosim("settle", str(half))))


def test_bad_files_get_one_line_and_exit_2(cli, tmp_path):
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello, not a recording\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    newer = tmp_path / "newer.mcap"
    run_id = new_run_id()
    with RecordingWriter(newer, run_id) as writer:
        writer.start({"schema_version": str(SCHEMA_VERSION + 1)})
        for key, payload in synthetic_day(run_id, 1, 1)[:5]:
            writer.write(key, payload, time.time_ns())
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(newer.read_bytes()[:6])
    info, settle, replay = ["info"], ["settle"], ["replay", "--rate", "max"]
    cases = [(not_mcap, "not an MCAP file", (info, settle, replay)), (newer, "newer than this dmosim", (info, settle,
             replay)), (empty, "not an MCAP file", (settle,)), (cut, "file cut after 6 bytes", (replay,)),
             (tmp_path / "missing.mcap", "no such file", (info,))]
    for path, words, commands in cases:
        for command in commands:
            assert words in one_line_error(cli(*command, str(path))), (command, path)
    assert "exists" in one_line_error(cli("run", "--record", str(newer)))  # never overwritten unasked


# --- crash safety ----------------------------------------------------------------------------------------------

def publish(bus: Bus, items) -> None:
    """Publish (key, payload) pairs as they are, blocking rather than dropping when Zenoh's queue is full."""
    publishers = {}
    for key, payload in items:
        if key not in publishers:
            publishers[key] = bus.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        publishers[key].put(payload)
    for publisher in publishers.values():
        publisher.undeclare()


@pytest.mark.slow
def test_a_recorder_killed_with_sigkill_loses_at_most_its_open_chunk(tmp_path):
    run_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{free_port()}"
    path, ready = tmp_path / "killed.mcap", tmp_path / "ready"
    mix = synthetic_day(run_id, 10, 2)  # a few hundred messages of every kind
    with Roles() as roles:
        recorder = roles.start("recorder", argv("record", "--out", str(path), "--run-id", run_id, "--mode", "router",
                                                "--listen", endpoint, "--ready-file", str(ready),
                                                "--flush-interval", "0.3", "--chunk-messages", "100"),
                               log=tmp_path / "recorder.log", env=ENV)
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert recorder.process.poll() is None and time.monotonic() < deadline, (tmp_path / "recorder.log").read_text()
            time.sleep(0.05)
        with Bus(run_id, "feeder", BusConfig(mode="client", connect=(endpoint,)), announce=False) as bus:
            assert bus.wait_for_subscribers(mix[0][0], 10)
            publish(bus, mix)
            deadline = time.monotonic() + 60  # the recorder closes its chunks within its flush interval
            while (readable := len(read_recording(path).messages)) < len(mix):
                assert time.monotonic() < deadline, f"{readable} of {len(mix)} messages readable after 60 s"
                time.sleep(0.05)
            publish(bus, mix[:50])
            roles.kill("recorder")
        assert recorder.process.wait(timeout=10) == -signal.SIGKILL
    rec = read_recording(path)
    assert not rec.complete and len(mix) <= len(rec.messages) <= len(mix) + 50
    assert [m.payload for m in rec.messages[:len(mix)]] == [p for _, p in mix]
    assert all(m.invalid is None for m in rec.messages)
    info = dmosim("info", str(path))
    assert info.returncode == 0 and f"file cut after {len(rec.messages)} messages" in info.stdout


def test_closed_chunks_keep_their_index_on_disk_and_the_file_is_mcaps_own(tmp_path, monkeypatch):
    """The writer keeps each closed chunk's index on disk as the bytes the summary will hold, not in memory as mcap's
    ChunkIndex with a dict of its channels; the file is byte for byte what mcap writes without that, and its summary
    reads back."""
    run_id = new_run_id()
    mix = synthetic_day(run_id, 20, 1)
    monkeypatch.setattr(time, "time_ns", lambda: 1_700_000_000_000_000_000)  # the header's and attachments' times
    paths, sizes = {}, {}
    for compact in (True, False):
        if not compact:
            monkeypatch.setattr(writer_module, "_spill_last_chunk_index", lambda writer, spill: None)
        paths[compact] = tmp_path / f"{compact}.mcap"
        writer = RecordingWriter(paths[compact], run_id, chunk_messages=25, flush_interval_s=3600)
        with monkeypatch.context() as m:  # the metadata's start time
            m.setattr(writer_module, "_dt", SimpleNamespace(datetime=SimpleNamespace(now=lambda tz: FIXED_START),
                                                            timezone=writer_module._dt.timezone))
            writer.start({"seed": "1"})
        for i, (key, payload) in enumerate(mix):
            writer.write(key, payload, 1_000_000_000 + i)
        indexes = writer._mcap._Writer__chunk_indices
        sizes[compact] = sum(deep_size(x) - (deep_size(x.spill) if compact else 0) for x in indexes) / len(indexes)
        assert all(isinstance(x, WrittenChunkIndex) for x in indexes) == compact and len(indexes) > 20
        writer.close()
    assert paths[True].read_bytes() == paths[False].read_bytes()
    # per chunk of 25 messages on about 20 channels: where its bytes are, against mcap's index (3.4 KiB)
    assert sizes[True] <= 128 and sizes[True] * 20 < sizes[False], sizes
    with open(paths[True], "rb") as f:
        summary = make_reader(f).get_summary()
    assert sum(c.message_index_offsets != {} for c in summary.chunk_indexes) == len(summary.chunk_indexes)
    assert read_recording(paths[True]).complete and len(read_recording(paths[True]).messages) == len(mix)


FIXED_START = datetime.datetime(2026, 7, 1, tzinfo=datetime.timezone.utc)


def deep_size(obj) -> int:
    """Bytes an object holds with what it refers to (dicts, dataclass fields, slots), counting each object once."""
    seen, stack, total = set(), [obj], 0
    while stack:
        o = stack.pop()
        if id(o) in seen:
            continue
        seen.add(id(o))
        total += sys.getsizeof(o)
        if isinstance(o, dict):
            stack += [*o.keys(), *o.values()]
        elif hasattr(o, "__dict__"):
            stack.append(vars(o))
        elif hasattr(type(o), "__slots__"):
            stack += [getattr(o, name) for name in type(o).__slots__]
    return total


def test_chunks_reach_the_disk_as_they_close_so_an_unfinished_file_reads(tmp_path):
    run_id, path = new_run_id(), tmp_path / "open.mcap"
    mix = synthetic_day(run_id, 2, 1)
    writer = RecordingWriter(path, run_id, chunk_messages=10, flush_interval_s=3600)
    writer.start({"seed": "1"})
    for key, payload in mix[:35]:
        writer.write(key, payload, time.time_ns())
    rec = read_recording(path)  # while the writer is still open, as after a SIGKILL
    assert not rec.complete and len(rec.messages) == 30 and rec.metadata["seed"] == "1"
    writer.tick(now=time.monotonic() + 7200)  # the open chunk is old enough: closed
    assert len(read_recording(path).messages) == 35
    writer.close()
    assert read_recording(path).complete


# --- invalid payloads --------------------------------------------------------------------------------------------

def test_an_invalid_payload_is_kept_with_its_reason_and_every_channel_still_fits_its_schema(tmp_path):
    run_id, path = new_run_id(), tmp_path / "faults.mcap"
    prefix = f"dmosim/{run_id}"
    good = synthetic_day(run_id, 1, 1)[:5]  # clock, registration, clock, call for bids, bid
    bad = [(f"{prefix}/agent/mg1/bid", b"{not json"),
           (f"{prefix}/agent/mg1/meter", good[1][1]),           # a registration on the meter key
           (f"{prefix}/dmo/grid", b'{"kind":"grid_state"}'),
           (f"{prefix}/somewhere/else", b'{"hello": 1}'),        # outside the layout but JSON: kept as is
           (f"{prefix}/{INVALID_KEY}", b"{}")]                  # nobody may publish on the recorder's own key
    with RecordingWriter(path, run_id) as writer:
        writer.start()
        for key, payload in good + bad:
            writer.write(key, payload, time.time_ns())
    rec = read_recording(path)
    invalid = [m for m in rec.messages if m.invalid]
    assert [(m.relative_key, m.payload) for m in invalid] == [(k.split("/", 2)[2], p) for k, p in bad if not
                                                              k.endswith("/else")]
    assert [m.invalid[0] for m in invalid] == ["not_json", "wrong_key", "invalid", "wrong_key"]
    assert "missing field" in invalid[2].invalid[1]
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            jsonschema.validate(json.loads(message.data), json.loads(schema.data))
            if channel.topic.endswith(INVALID_KEY):
                wrapped = json.loads(message.data)
                assert base64.b64decode(wrapped["payload_base64"]) in {p for _, p in bad}
    replayed = select(rec, ["agent/*/bid"])  # replay sends the fault as it arrived, on its own key
    assert [m.payload for m in replayed] == [good[4][1], b"{not json"]


def test_key_patterns_match_levels_like_zenoh_and_parts_like_globs():
    cases = {"dmo/*": (["dmo/clock", "dmo/grid"], ["dmo/award/mg1", "agent/mg1/bid"]),
             "agent/*/meter": (["agent/mg1/meter", "agent/x/meter"], ["agent/mg1/bid", "agent/a/b/meter"]),
             "dmo/award/mg*": (["dmo/award/mg1", "dmo/award/mg22"], ["dmo/award/x1"]),
             "**/mg1/**": (["agent/mg1/bid", "dmo/award/mg1/x"], ["agent/mg2/bid"]),
             "dmo/**": (["dmo/clock", "dmo/award/mg1"], ["agent/mg1/bid"])}
    for pattern, (matching, other) in cases.items():
        compiled = key_pattern(pattern)
        assert all(compiled.match(k) for k in matching), pattern
        assert not any(compiled.match(k) for k in other), pattern


# --- replay ----------------------------------------------------------------------------------------------------

class Tap:
    """A router bus listening under one run prefix, counting payloads per key relative to it."""

    def __init__(self, run_id: str, endpoint: str):
        self.bus = Bus(run_id, "tap", BusConfig(mode="router", listen=(endpoint,)), announce=False)
        self.payloads: dict[str, list[bytes]] = collections.defaultdict(list)
        self.lock = threading.Condition()

    def __enter__(self) -> Tap:
        self.bus.open()
        prefix = self.bus.keys.prefix + "/"
        self.bus.subscribe_raw(self.bus.keys.everything(), self.on_sample)
        self.prefix = prefix
        return self

    def on_sample(self, key, payload, at):
        with self.lock:
            self.payloads[key[len(self.prefix):]].append(payload)
            self.lock.notify_all()

    def wait_for(self, total: int, timeout: float = 60.0) -> None:
        """Until ``total`` payloads have arrived (replays end before their last samples reach the tap)."""
        with self.lock:
            assert self.lock.wait_for(lambda: sum(map(len, self.payloads.values())) >= total, timeout), \
                f"{sum(map(len, self.payloads.values()))} of {total} payloads arrived"

    def counts(self) -> collections.Counter:
        with self.lock:
            return collections.Counter({k: len(v) for k, v in self.payloads.items()})

    def __exit__(self, *exc) -> None:
        self.bus.close()


def _replay(path: Path, run_id: str, endpoint: str, *flags: str) -> dict:
    out = dmosim("replay", str(path), "--run-id", run_id, "--mode", "client", "--connect", endpoint, "--json", *flags)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout)


@pytest.mark.slow
def test_replay_republishes_every_message_under_a_new_prefix_at_full_rate(day):
    rec = read_recording(day[0])
    run_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{free_port()}"
    assert run_id != rec.run_id
    with Tap(run_id, endpoint) as tap:
        result = _replay(day[0], run_id, endpoint, "--rate", "max")
        tap.wait_for(len(rec.messages))
        assert result["published"] == len(rec.messages) and result["key_prefix"] == f"dmosim/{run_id}"
        assert tap.counts() == collections.Counter(m.relative_key for m in rec.messages)
        assert tap.payloads["agent/mg1/meter"] == [m.payload for m in rec.in_log_order()
                                                   if m.relative_key == "agent/mg1/meter"]


@pytest.mark.slow
def test_replay_selects_topics_and_start_offset_and_keeps_the_spacing_scaled_by_the_rate(day):
    rec = read_recording(day[0])
    first = rec.in_log_order()[0].log_time
    offset = (rec.in_log_order()[-1].log_time - first) / 2e9
    chosen = [m for m in rec.in_log_order() if m.log_time >= first + offset * 1e9
              and (m.relative_key.endswith("/meter") or m.relative_key == "dmo/grid")]
    run_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{free_port()}"
    with Tap(run_id, endpoint) as tap:
        result = _replay(day[0], run_id, endpoint, "--topics", "agent/*/meter", "--topics", "dmo/grid",
                         "--start-offset", repr(offset), "--rate", "40")
        tap.wait_for(len(chosen))
        assert tap.counts() == collections.Counter(m.relative_key for m in chosen)
    span_s = (chosen[-1].log_time - chosen[0].log_time) / 1e9
    assert result["seconds"] >= span_s / 40 - 1e-3  # it waits for the recorded gaps, 40 times shorter (seconds are printed to 3 decimals)


def _small_recording(tmp_path: Path) -> tuple[Path, list]:
    """A synthetic day of one agent written as a recording, its messages 1 ms apart; the path and the messages."""
    run_id, path = new_run_id(), tmp_path / "small.mcap"
    mix = synthetic_day(run_id, 1, 1)
    with RecordingWriter(path, run_id) as writer:
        writer.start()
        for i, (key, payload) in enumerate(mix):
            writer.write(key, payload, 1_000_000_000 + i * 1_000_000)
    return path, mix


@pytest.mark.slow
def test_replay_loops_until_interrupted(tmp_path):
    path, mix = _small_recording(tmp_path)
    replay_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{free_port()}"
    with Tap(replay_id, endpoint) as tap:
        player = subprocess.Popen(argv("replay", str(path), "--loop", "--rate", "4", "--run-id", replay_id, "--mode",
                                       "client", "--connect", endpoint, "--json"),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV,
                                  start_new_session=True)
        try:
            tap.wait_for(2 * len(mix))
            player.send_signal(signal.SIGINT)
            out, err = player.communicate(timeout=30)
        finally:
            if player.poll() is None:
                os.killpg(player.pid, signal.SIGKILL)
                player.wait()
    assert player.returncode == 0, err[-2000:]
    result = json.loads(out)
    assert result["loops"] >= 2 and result["interrupted"] and result["published"] >= 2 * len(mix)


@pytest.mark.slow
def test_replay_says_when_nobody_listens_and_plays_all_the_same(tmp_path):
    path, mix = _small_recording(tmp_path)
    out = dmosim("replay", str(path), "--run-id", new_run_id(), "--mode", "router", "--listen",
                 f"tcp/127.0.0.1:{free_port()}", "--rate", "max", "--wait-for-subscriber", "0.3", "--json")
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    assert result["subscribed"] is False and result["published"] == result["selected"] == len(mix)


@pytest.mark.slow
def test_replay_as_dmo_lets_a_live_agent_take_part_and_settles_it(day, tmp_path, listener):
    rec = read_recording(day[0])
    experiment = tmp_path / "experiment.toml"  # the run's own, as its run directory keeps it
    experiment.write_bytes(next(a for a in rec.attachments if a.name == "experiment.toml").data)
    run_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{listener.port}"
    out_path, recording = tmp_path / "as_dmo.json", tmp_path / "as_dmo.mcap"
    with Roles() as roles, open(out_path, "w") as out:
        # the agent starts first, as a user may: it keeps trying to connect until the DMO's side listens
        log = tmp_path / "mg2.log"
        roles.start("mg2", argv("agent", "--experiment", str(experiment), "--id", "mg2", "--run-id", run_id,
                                "--market-day", DAY, "--connect", endpoint), log=log, env=ENV)
        listener.accept()  # it tries: nothing there answers as a DMO would
        listener.close()  # its try fails, and the DMO's side takes the port
        player = subprocess.Popen(argv("replay", str(day[0]), "--as-dmo", "--agent", "mg2", "--run-id", run_id,
                                       "--listen", endpoint, "--record", str(recording), "--timeout", "120", "--json",
                                       "--insecure"),
                                  stdout=out, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV,
                                  start_new_session=True)
        try:
            _, err = player.communicate(timeout=600)
        finally:
            if player.poll() is None:
                os.killpg(player.pid, signal.SIGKILL)
                player.wait()
        assert player.returncode == 0, err[-3000:]
        assert roles.roles["mg2"].process.wait(timeout=60) == 0, (tmp_path / "mg2.log").read_text()[-2000:]
    result = json.loads(out_path.read_text())
    assert result["agent"] == "mg2" and result["meter_reports"] == 24 and result["incidents"] == []
    recorded = {m.agent: m for _, m in rec.decoded("settlement_statement")}["mg2"]
    # the same agent (code, seed, case) against the same award and grid: the same bill, to the cent
    assert result["statement"]["total"] == recorded.total and result["difference"] == 0
    assert dmosim("settle", str(recording)).returncode == 0  # its own recording re-settles to the same statement
    mine = read_recording(recording)
    # distinct payloads: an agent sends a payload again, the same bytes, while its receipt is on its way
    counts = collections.Counter(key for key, _ in {(m.relative_key, m.payload) for m in mine.messages})
    assert counts["agent/mg2/meter"] == 24 and counts["dmo/grid"] == 24 and "dmo/award/mg1" not in counts
    assert mine.run_id == run_id
    assert {a.name for a in mine.attachments} == {"experiment.toml", "paper.toml", "fleet.toml"}


@pytest.mark.slow
def test_replay_as_dmo_keeps_the_credentials_it_makes_only_while_it_runs(tmp_path):
    """Given no --auth-dir, replay --as-dmo makes the run's credentials in a private temporary directory (the one
    the agent's --auth-dir names while the replay lasts) and removes them as it ends: nothing is left where it ran,
    nor in the temporary directory."""
    path, _ = _small_recording(tmp_path)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    out = subprocess.run(argv("replay", str(path), "--as-dmo", "--timeout", "0.2", "--listen",
                              f"tcp/127.0.0.1:{free_port()}", "--quiet"),
                         capture_output=True, text=True, cwd=tmp_path, env={**ENV, "TMPDIR": str(scratch)}, timeout=120)
    assert out.returncode == 1, out.stderr[-2000:]  # nobody registered within the timeout: a runtime failure
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.mcap", "tmp"]
    assert list(scratch.iterdir()) == []


# --- determinism -----------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_the_same_configuration_and_seed_record_the_same_contents(day, tmp_path):
    again, result = run_day(tmp_path)
    first, second = read_recording(day[0]), read_recording(again)
    assert first.run_id != second.run_id
    assert content_signature(first) == content_signature(second)


@contextlib.contextmanager
def recorder_beside_a_dmo(tmp_path, name: str, run_id: str, answer):
    """A DMO bus answering queries with ``answer(key, parameters)`` and a recorder that joined before anything was
    said, writing ``name`` under ``tmp_path`` on its own thread; the recorder is stopped when the block ends."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with Bus(run_id, "dmo", BusConfig(mode="router", listen=[endpoint])) as dmo:
        dmo.serve(dmo.keys.everything(), answer)
        with Bus(run_id, "recorder", BusConfig(mode="client", connect=[endpoint]), announce=False) as bus:
            recorder = Recorder(bus, RecordingWriter(tmp_path / name, run_id))
            recorder.writer.start({}, [])
            assert recorder.start() == 0  # joined before anything was said
            stop = threading.Event()
            loop = threading.Thread(target=recorder.run, args=(stop,))
            loop.start()
            try:
                yield dmo, recorder
            finally:
                stop.set()
                loop.join(30)


def test_what_the_recorder_remembers_to_catch_up_is_two_days_not_the_run():
    """The payloads the recorder notes as they come (to tell what catching up must add) are those since the DMO's
    history was checked the day before: each day summary's check moves the window on, however many days the run
    has, and a payload that came just before a check is still known as come."""
    run_id = new_run_id()
    answers: list = []
    bus = SimpleNamespace(keys=Keys(run_id), replies=lambda selector, timeout_s: iter(answers.pop(0)))
    recorder = Recorder(bus, writer=None)
    per_day = []
    for day in range(1, 8):
        entries = [(key, payload, time.time_ns() - 10**10)  # as the DMO saw them, 10 s ago
                   for key, payload in synthetic_day(run_id, 3, 1, market_day=f"2026-07-0{day}", seed=day)]
        for key, payload, _ in entries:
            recorder._received(key, payload, time.time_ns())  # as the subscription delivers it
        answers.append(entries)
        per_day.append(len(entries))
        held = len(recorder.seen)  # this day's and the day before's
        assert held == sum(per_day[-2:])
        assert recorder._check_history() == 0  # everything came
        assert recorder.seen.since == max(at for _, _, at in entries) + 1
        assert all((key, payload) in recorder.seen for key, payload, _ in entries)
        assert (entries[0][0], b"never sent") not in recorder.seen
    assert recorder._queue.qsize() == sum(per_day)  # every payload of the week, to be written, none twice
    assert held < sum(per_day) / 3


def test_the_recorder_queues_what_never_came_as_each_reply_of_the_dmos_traffic_comes():
    """A day's traffic of a thousand agents is a few hundred thousand replies: the recorder takes each as it comes,
    not the whole answer first."""
    run_id = new_run_id()
    entries = [(key, payload, time.time_ns() - 10**10) for key, payload in synthetic_day(run_id, 2, 1)]
    recorder = None

    def replies(selector, timeout_s):
        for queued, entry in enumerate(entries):
            assert recorder._queue.qsize() == queued  # the ones before are queued already
            yield entry

    recorder = Recorder(SimpleNamespace(keys=Keys(run_id), replies=replies), writer=None)
    assert recorder._check_history() == len(entries) == recorder._queue.qsize()


@pytest.mark.slow
def test_on_each_day_summary_the_recorder_checks_the_dmos_traffic_since_the_last_and_records_what_never_came(
        tmp_path):
    """An agent's registration the DMO received but the recorder never did (a router link went down between them)
    is recorded from the DMO's history on the day summary, with the DMO's time; what came live is not again, and
    the next check asks only for what the DMO saw after the last time the first answer held."""
    run_id = new_run_id()
    day = synthetic_day(run_id, 2, 1)
    lost, came, summary = (next(e for e in day if e[0].endswith(k)) for k in ("/agent/mg2/register",
                                                                                "/agent/mg1/register", "/dmo/summary"))
    seen_at = time.time_ns() - 10 * 10**9
    history = [(lost[0], lost[1], seen_at), (came[0], came[1], seen_at + 1), (summary[0], summary[1], seen_at + 2)]
    asked: list[str] = []

    def answer(key: str, parameters: str) -> list:
        asked.append(parameters)
        return history if "since=" in parameters else []  # nothing was said before the recorder joined

    done = threading.Event()
    with recorder_beside_a_dmo(tmp_path, "checked.mcap", run_id, answer) as (dmo, recorder):
        assert dmo.wait_for_subscribers(summary[0], 10)
        dmo.publish_raw(came[0], came[1])  # arrives; the other registration was lost on its way
        dmo.publish_raw(summary[0], summary[1])
        deadline = time.monotonic() + 30
        while recorder.seen.since == 0 and time.monotonic() < deadline:
            done.wait(0.1)
        dmo.publish_raw(summary[0], summary[1])  # the next day's check
        while sum("since" in a for a in asked) < 2 and time.monotonic() < deadline:
            done.wait(0.1)
    rec = read_recording(tmp_path / "checked.mcap")
    assert recorder.caught_up == 1
    assert [(m.relative_key, m.log_time) for m in rec.messages if m.kind == "registration"] == [
        ("agent/mg1/register", rec.messages[0].log_time), ("agent/mg2/register", seen_at)]
    assert sum(m.kind == "day_summary" for m in rec.messages) == 2  # what came live is not caught up again
    assert [a for a in asked if "since" in a] == ["history;since=0", f"history;since={seen_at + 3}"]


def test_the_recorder_stops_on_a_signal_whose_handler_runs_late(tmp_path):
    """SIGTERM's handler sets the recorder's stop; on a loaded machine it may run after the writing loop's wait for
    the next payload should have ended. The loop still sees the stop and the file is finished (a queue whose timed
    get blocked for good then left a CI run's recorder stuck until its 30 s watchdog)."""
    run_id = new_run_id()
    writer = RecordingWriter(tmp_path / "late.mcap", run_id)
    writer.start({}, [])
    recorder = Recorder(SimpleNamespace(keys=Keys(run_id)), writer)
    stop = threading.Event()
    previous = signal.signal(signal.SIGUSR1, lambda *_: (stop.set(), time.sleep(0.15)))  # a late handler
    threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGUSR1)).start()
    rescue = threading.Timer(5.0, recorder._queue.put, ((f"{Keys(run_id).prefix}/dmo/clock", b"{}", 0, True),))
    rescue.start()  # a loop that missed the stop is woken by a payload, so that this test fails instead of hanging
    began = time.monotonic()
    try:
        recorder.run(stop)
    finally:
        rescue.cancel()
        signal.signal(signal.SIGUSR1, previous)
    assert time.monotonic() - began < 2.0
    assert read_recording(tmp_path / "late.mcap").complete
