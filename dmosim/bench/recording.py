"""Recording: the recorder's sustained write rate, replay at maximum rate, and the size of a recorded agent-day.

The messages are those of a real market day (``synthetic_day``: every kind, real schemas, settlement statements
from ``dmo.market.settlement``), built without solving anything. Figures:

- ``write``: messages/s through ``RecordingWriter`` alone (validation, chunking, zstd, a chunk closed every
  ``chunk_messages``), and end to end: a ``dmosim record`` process receiving the mix over Zenoh from a publisher
  in this process, measured from the file it wrote (messages over their log-time span; lost = sent - recorded);
- ``replay``: ``dmosim replay --rate max`` of that file, timed by a subscriber here that counts what arrives;
- ``size``: bytes of one recorded day per agent, zstd-compressed, from days of 1 and N agents.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from dmo.market.settlement import settle
from dmo.operator.outbox import day_summary, statement_message
from messages import (DMO, Award, Bid, BidStep, CallForBids, Clock, GridState, MeterReport, Registration, Schedule,
                      encode)
from messages.keys import Keys, new_run_id
from messages.schemas import PRICE_CAP, PRICE_FLOOR
from messages.recording import CHUNK_MESSAGES, RecordingWriter, read_recording

from ..arguments import positive_int
from ..console import stopping_on_terminate
from ..launch.processes import dmosim_command, role_env
from ..launch.roles import EXPORT_LIMIT_PER_AGENT, IMPORT_LIMIT_PER_AGENT

GOAL_MSGS_S = 20_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--messages", type=positive_int, default=100_000,
                        help="messages per write-rate measurement (default: 100000)")
    parser.add_argument("--agents", type=positive_int, default=10, help="agents of the day whose mix is used (default: 10)")
    parser.add_argument("--subperiods", type=positive_int, default=6, help="sub-periods per hour (default: 6)")
    parser.add_argument("--chunk-messages", type=positive_int, default=CHUNK_MESSAGES,
                        help=f"messages per chunk, as the recorder (default: {CHUNK_MESSAGES})")


def run(args) -> dict:
    scratch = Path(tempfile.mkdtemp(prefix="dmosim-bench-recording-"))
    try:
        mix = synthetic_day(new_run_id(), args.agents, args.subperiods)
        writer = writer_rate(mix, args.messages, args.chunk_messages, scratch / "writer.mcap")
        cost = cost_split(mix, args.messages)
        wire = wire_rate(mix, args.messages, args.chunk_messages, scratch)
        replay = replay_rate(wire.pop("path"), scratch)
        size = day_size(args.agents, args.subperiods, scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return {
        "setup": {"mix": f"one market day of {args.agents} agents, K={args.subperiods}, repeated: "
                         f"{len(mix)} messages, mean {sum(len(p) for _, p in mix) / len(mix):.0f} bytes",
                  "chunk_messages": args.chunk_messages, "machine": f"{os.cpu_count()} cores shared with other work"},
        "write": [{"path": "RecordingWriter alone", **writer},
                  {"path": "Zenoh -> dmosim record", **{k: v for k, v in wire.items()
                                                       if k not in ("lost", "publisher_msgs_per_s")}}],
        "cpu_us_per_message": cost,
        "publisher_msgs_per_s": wire["publisher_msgs_per_s"],
        "lost_over_zenoh": wire["lost"],
        "replay": replay,
        "size": size,
        "goal": {"msgs_per_s": GOAL_MSGS_S, "writer_met": writer["msgs_per_s"] >= GOAL_MSGS_S,
                 "end_to_end_met": wire["msgs_per_s"] >= GOAL_MSGS_S},
    }


# --- a realistic day -------------------------------------------------------------------------------------------

def synthetic_day(run_id: str, agents: int, subperiods: int = 6, market_day: str = "2026-07-01",
                  seed: int = 0) -> list[tuple[str, bytes]]:
    """Every message of one market day of ``agents`` agents, in the order of the day, as (key, payload):
    stamped as a Bus would, with realistic numbers; statements settled by ``dmo.market.settlement``."""

    rng = np.random.default_rng(seed)
    keys = Keys(run_id)
    names = [f"mg{i}" for i in range(1, agents + 1)]
    out: list[tuple[str, bytes]] = []
    seqs: dict[str, int] = {}
    clock = [time.time_ns()]

    def put(msg) -> None:
        clock[0] += 1_000_000
        seq = seqs.get(msg.sender, 0)
        seqs[msg.sender] = seq + 1
        msg = msg.model_copy(update={"seq": seq, "sent_at": clock[0]})
        out.append((keys.for_message(msg), encode(msg)))

    def hourly(lo: float, hi: float) -> tuple[float, ...]:
        return tuple(round(float(x), 4) for x in rng.uniform(lo, hi, 24))

    prices, k = hourly(20, 90), subperiods
    penalty, cap = 150.0, 10.0
    put(Clock(sender=DMO, market_day=market_day, phase="registration", deadline_s=60.0, day=1, days=1))
    for a in names:
        put(Registration(sender=a, market_day=market_day, case="paper", max_import_mw=cap, max_export_mw=cap))
    put(Clock(sender=DMO, market_day=market_day, phase="bidding", deadline_s=600.0, day=1, days=1))
    put(CallForBids(sender=DMO, market_day=market_day, iso_price_per_mwh=prices, price_floor_per_mwh=PRICE_FLOOR,
                    price_cap_per_mwh=PRICE_CAP, import_limit_mw=IMPORT_LIMIT_PER_AGENT * agents,
                    export_limit_mw=EXPORT_LIMIT_PER_AGENT * agents,
                    penalty_per_mwh=penalty, subperiods=k, deadline_s=600.0))
    for a in names:
        put(Bid(sender=a, market_day=market_day, hours=tuple(
            tuple(BidStep(price_per_mwh=round(float(p), 3), quantity_mw=round(float(q), 4))
                  for p, q in zip(np.sort(rng.uniform(10, 120, 4))[::-1], rng.uniform(-2, 4, 4))) for _ in range(24))))
    put(Clock(sender=DMO, market_day=market_day, phase="clearing", deadline_s=600.0, day=1, days=1))
    awards = {a: hourly(-2, 6) for a in names}
    for a in names:
        put(Award(sender=DMO, market_day=market_day, agent=a, p_sch_mw=awards[a], clearing_price_per_mwh=prices,
                  penalty_per_mwh=penalty, subperiods=k, rules_version=1,
                  rules="energy charge = clearing price x award per hour; penalty = c x max(P_M - P_sch, 0) x dt"))
    put(Clock(sender=DMO, market_day=market_day, phase="scheduling", deadline_s=1800.0, day=1, days=1))
    for a in names:
        put(Schedule(sender=a, market_day=market_day, status="optimal",
                     commitment={f"G{i}": tuple(int(x) for x in rng.integers(0, 2, 24)) for i in range(1, 5)},
                     expected_cost=round(float(rng.uniform(1e3, 5e3)), 2), p_m_expected_mw=hourly(-2, 6),
                     scenarios=10, mip_gap=0.004))
    meter: dict[str, dict[int, tuple[float, ...]]] = {a: {} for a in names}
    for hour in range(1, 25):
        put(Clock(sender=DMO, market_day=market_day, phase="realtime", hour=hour, deadline_s=300.0, day=1, days=1))
        put(GridState(sender=DMO, market_day=market_day, hour=hour, subperiods=k, connected=(hour != 12,) * k))
        for a in names:
            p_m = tuple(round(float(x), 6) for x in awards[a][hour - 1] + rng.normal(0, 0.3, k))
            meter[a][hour - 1] = p_m
            put(MeterReport(sender=a, market_day=market_day, hour=hour, subperiods=k, p_m_mw=p_m,
                            deviation_mw=tuple(round(p - awards[a][hour - 1], 6) for p in p_m)))
    put(Clock(sender=DMO, market_day=market_day, phase="settlement", deadline_s=300.0, day=1, days=1))
    statements, _ = settle(awards, prices, meter, subperiods=k, penalty=penalty, p_m_max=cap)
    for st in statements.values():
        put(statement_message(st, market_day, penalty, 0.0))
    put(day_summary(market_day, names, prices, statements, 0, ()))
    return out


def _messages(mix: list[tuple[str, bytes]], n: int):
    for i in range(n):
        yield mix[i % len(mix)]


# --- measurements ----------------------------------------------------------------------------------------------

def writer_rate(mix, n: int, chunk_messages: int, path: Path) -> dict:
    run_id = mix[0][0].split("/")[1]
    start, cpu = time.perf_counter(), time.process_time()
    with RecordingWriter(path, run_id, chunk_messages=chunk_messages) as writer:
        writer.start()
        for key, payload in _messages(mix, n):
            writer.write(key, payload, time.time_ns())
            writer.tick()
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    return {"messages": n, "seconds": round(elapsed, 3), "msgs_per_s": round(n / elapsed),
            "msgs_per_cpu_s": round(n / cpu), "mb_per_s": round(sum(len(p) for _, p in _messages(mix, n)) / elapsed / 1e6, 2)}


def cost_split(mix, n: int) -> dict:
    """CPU microseconds per message of the recorder's two steps, each alone: validating the payload against its
    key's kind (``decode``) and adding it to an MCAP chunk (mcap's writer, zstd included)."""
    import io  # noqa: PLC0415

    from mcap.writer import Writer  # noqa: PLC0415

    from messages.codec import decode  # noqa: PLC0415
    from messages.keys import parse_key  # noqa: PLC0415

    kinds = [parse_key(key).kind for key, _ in mix]
    cpu = time.process_time()
    for i in range(n):
        decode(mix[i % len(mix)][1], expected_kind=kinds[i % len(mix)])
    validate = time.process_time() - cpu
    writer = Writer(io.BytesIO())
    writer.start()
    channel = writer.register_channel("t", "json", writer.register_schema("s", "jsonschema", b"{}"))
    cpu = time.process_time()
    for i in range(n):
        writer.add_message(channel, log_time=i, data=mix[i % len(mix)][1], publish_time=i)
        if i % CHUNK_MESSAGES == CHUNK_MESSAGES - 1:
            writer.flush()
    writer.finish()
    write = time.process_time() - cpu
    heavy = {k for k in kinds if k in ("bid", "settlement_statement")}
    share = sum(1 for k in kinds if k in heavy) / len(kinds)
    return {"validate": round(validate / n * 1e6, 1), "mcap_write": round(write / n * 1e6, 1),
            "bids_and_statements_share_of_messages": round(share, 3)}




def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process so far (Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wire_rate(mix, n: int, chunk_messages: int, scratch: Path) -> dict:
    """A ``dmosim record`` process listening; this process publishes n messages as fast as Zenoh takes them
    (congestion control BLOCK: the publisher slows rather than drops). The recorder's sustained rate is what it
    wrote over the span from its first receipt to its last write (its own log line), so a backlog it is still
    working through counts against it; its CPU time is read from /proc."""
    import zenoh  # noqa: PLC0415

    from dmosim.launch.processes import Roles, free_port  # noqa: PLC0415
    from messages.transport import Bus, BusConfig  # noqa: PLC0415

    run_id = mix[0][0].split("/")[1]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    path, ready, log = scratch / "wire.mcap", scratch / "ready", scratch / "recorder.log"
    with stopping_on_terminate(), Roles() as roles:  # SIGTERM as Ctrl-C: the recorder is stopped on the way out
        recorder = roles.start("recorder", dmosim_command("record", "--out", str(path), "--run-id", run_id, "--mode", "router",
                                                   "--listen", endpoint, "--ready-file", str(ready),
                                                   "--chunk-messages", str(chunk_messages)), log=log, env=role_env())
        _wait_file(ready, recorder.process, 60)
        cpu_before = _cpu_s(recorder.process.pid)
        with Bus(run_id, "bench", BusConfig(mode="client", connect=(endpoint,)), announce=False) as bus:
            publishers = {}
            for key, _ in mix:
                if key not in publishers:
                    publishers[key] = bus.session.declare_publisher(
                        key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.BLOCK)
            bus.wait_for_subscribers(mix[0][0], 10)
            start = time.perf_counter()
            for key, payload in _messages(mix, n):
                publishers[key].put(payload)
            sent_s = time.perf_counter() - start
            # This session stays open until the recorder has worked through its backlog (its file stops growing
            # while it closes a chunk at least every flush interval): closing it earlier drops what Zenoh still
            # holds in flight, which would be counted as lost.
            deadline, last = time.monotonic() + 120, -1
            while time.monotonic() < deadline:
                size = path.stat().st_size
                if size == last:
                    break
                last = size
                time.sleep(1.5)
            for p in publishers.values():
                p.undeclare()
        cpu_s = _cpu_s(recorder.process.pid) - cpu_before
        recorder.process.send_signal(signal.SIGTERM)
        recorder.process.wait(timeout=60)
    found = re.search(r"recorded (\d+) messages .*; ([0-9.]+) s from the first receipt", log.read_text())
    if not found:
        raise RuntimeError(f"the recorder did not report its figures; its log: {log}")
    written, span = int(found.group(1)), float(found.group(2))
    return {"messages": written, "seconds": round(span, 3), "msgs_per_s": round(written / span),
            "msgs_per_cpu_s": round(written / cpu_s) if cpu_s > 0 else None,
            "mb_per_s": round(sum(len(p) for _, p in _messages(mix, written)) / span / 1e6, 2),
            "publisher_msgs_per_s": round(n / sent_s), "lost": n - written, "path": path}


def replay_rate(path: Path, scratch: Path) -> dict:
    """``dmosim replay --rate max`` of a recording to a subscriber here; rate from the subscriber's clock."""
    from dmosim.launch.processes import Roles, free_port  # noqa: PLC0415
    from messages.transport import Bus, BusConfig  # noqa: PLC0415

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    run_id = new_run_id()
    total = len(read_recording(path).messages)
    got = {"n": 0, "first": 0.0, "last": 0.0}
    lock, done = threading.Lock(), threading.Event()

    def on_sample(key, payload, at):
        with lock:
            now = time.perf_counter()
            got["first"] = got["first"] or now
            got["n"] += 1
            got["last"] = now
            if got["n"] >= total:
                done.set()

    # SIGTERM as Ctrl-C: the player is stopped on the way out
    with stopping_on_terminate(), Bus(run_id, "tap", BusConfig(mode="router", listen=(endpoint,)),
                                      announce=False) as bus, Roles() as roles:
        bus.subscribe_raw(bus.keys.everything(), on_sample)
        start = time.perf_counter()
        player = roles.start("replay", dmosim_command("replay", str(path), "--rate", "max", "--run-id", run_id, "--mode",
                                               "client", "--connect", endpoint, "--quiet"),
                             log=scratch / "replay.log", env=role_env())
        done.wait(120)
        code = player.process.wait(timeout=60)
        process_s = time.perf_counter() - start
    span = got["last"] - got["first"]
    return {"messages": total, "received": got["n"], "seconds": round(span, 3),
            "msgs_per_s": round(got["n"] / span) if span > 0 else None,
            "process_s": round(process_s, 2), "exit": code}


def day_size(agents: int, subperiods: int, scratch: Path) -> dict:
    rows = {}
    for n in sorted({1, agents}):
        mix = synthetic_day(new_run_id(), n, subperiods)
        path = scratch / f"day{n}.mcap"
        with RecordingWriter(path, mix[0][0].split("/")[1]) as writer:
            writer.start()
            for key, payload in mix:
                writer.write(key, payload, time.time_ns())
        rows[n] = (path.stat().st_size, sum(len(p) for _, p in mix), len(mix))
    size_1, json_1, _ = rows[1]
    size_n, json_n, msgs_n = rows[agents]
    marginal = (size_n - size_1) / (agents - 1) if agents > 1 else size_1
    return {"subperiods": subperiods, "day_of_1_agent_bytes": size_1,
            f"day_of_{agents}_agents_bytes": size_n, "messages": msgs_n,
            "bytes_per_agent_day": round(size_n / agents), "marginal_bytes_per_agent_day": round(marginal),
            "json_bytes_per_agent_day": round(json_n / agents), "compression_ratio": round(json_n / size_n, 2)}


def _wait_file(path: Path, process: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if process.poll() is not None:
            raise RuntimeError(f"the recorder exited ({process.returncode}) before it was ready")
        if time.monotonic() > deadline:
            raise RuntimeError("the recorder was not ready in time")
        time.sleep(0.05)
