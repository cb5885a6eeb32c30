"""Round-trip latency and one-way throughput of our message layer (Bus: stamp, encode, validate) between two processes.

The benchmark process is the Zenoh router and plays the DMO; a second OS process (``python -m dmosim.bench.messaging
--echo``) connects as client and plays agent ``mg1``. Both hand what arrives from Zenoh's callback thread to their
main thread through a queue, as the DMO and the agents do, and the same measurements are repeated with plain
Zenoh puts of the same bytes on the same sessions, so the ratio isolates what our layer adds. The two processes
talk out of band (the echo process's stdin and stdout) to start a burst and report on it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import queue
import subprocess
import sys
import threading
import time

import numpy as np

from messages import GridState, MeterReport, decode, encode
from messages.keys import new_run_id
from messages.schemas import DMO
from messages.transport import Bus, BusConfig, wait_matching

from ..arguments import positive_int
from ..console import stopping_on_terminate
from ..launch.processes import ROLE_STOP_S, free_port, interrupts_held, role_env, stop_processes

AGENT = "mg1"
TIMEOUT_S = 30.0  # for any single reply or handshake: a dead peer fails the bench instead of hanging it
QUIT_S = 5.0  # how long the echo process has to quit once its input ends, before it is stopped


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--messages", type=positive_int, default=2000,
                        help="round trips, one at a time (default: 2000)")
    parser.add_argument("--burst", type=positive_int, default=20000,
                        help="messages in the throughput burst (default: 20000)")
    parser.add_argument("--warmup", type=int, default=100, help="round trips run first and not counted (default: 100)")
    parser.add_argument("--subperiods", type=positive_int, default=6,
                        help="sub-periods per GridState / MeterReport, i.e. message size (default: 6)")
    parser.add_argument("--codec-iterations", type=positive_int, default=5000,
                        help="encodes and decodes timed per message kind (default: 5000)")


def run(args) -> dict:
    market_day = dt.date.today().isoformat()
    k = args.subperiods
    grid = grid_state(market_day, k)
    report = meter_report(grid)
    out: dict = {"setup": {
        "processes": "benchmark = Zenoh router (DMO side), echo = client (agent mg1), TCP on loopback",
        "subperiods": k, "round_trips": args.messages, "warmup": args.warmup, "burst": args.burst,
        "machine": f"{os.cpu_count()} cores shared with other work: figures from one run, noisy",
    }}
    out["codec_us"] = [codec_row(grid, args.codec_iterations), codec_row(report, args.codec_iterations)]

    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # SIGTERM as Ctrl-C while the echo process runs: it is stopped on the way out (Echo.__exit__).
    with stopping_on_terminate(), Bus(run_id, DMO, BusConfig(mode="router", listen=(endpoint,))) as bus:
        raw = bus.keys.prefix + "/bench"
        replies: queue.Queue = queue.Queue()
        bus_count, raw_count = Counter(), Counter()

        def on_report(key, msg, received_at):  # round trips hand the reply to the main thread; bursts just count
            if bus_count.active:
                bus_count.tick()
            else:
                replies.put(msg)

        with bus.subscribe(bus.keys.meter(AGENT), on_report), \
                bus.session.declare_subscriber(f"{raw}/pong", lambda s: replies.put(s.payload.to_bytes())), \
                bus.session.declare_subscriber(f"{raw}/burst", lambda s: raw_count.tick(s.payload.to_bytes())), \
                bus.session.declare_publisher(f"{raw}/ping") as ping, \
                Echo(run_id, endpoint, market_day) as echo:
            if not bus.wait_for_subscribers(bus.keys.grid(), TIMEOUT_S) or not wait_matching(ping, TIMEOUT_S):
                raise RuntimeError("the echo process did not subscribe in time")
            bus_rtt = round_trips(args, lambda i: bus.publish(grid.model_copy(update={"hour": i % 24 + 1})),
                                  replies, check=lambda i, msg: msg.hour == i % 24 + 1)
            payload = encode(grid)
            raw_rtt = round_trips(args, lambda i: ping.put(payload), replies, check=lambda i, got: got == payload)
            bus_tp = burst(echo, "burst", args.burst, k, bus_count)
            raw_tp = burst(echo, "raw", args.burst, k, raw_count)

    out["round_trip_ms"] = [{"path": "dmosim Bus", **bus_rtt}, {"path": "plain zenoh", **raw_rtt}]
    out["throughput"] = [{"path": "dmosim Bus", **bus_tp}, {"path": "plain zenoh", **raw_tp}]
    out["ratios"] = {
        "round_trip_p50_bus_over_zenoh": bus_rtt["p50"] / raw_rtt["p50"],
        "throughput_bus_over_zenoh": bus_tp["received_per_s"] / raw_tp["received_per_s"],
    }
    out["goal"] = {"p50_round_trip_ms": bus_rtt["p50"], "target_ms": 1.0, "met": bus_rtt["p50"] <= 1.0}
    return out


def grid_state(market_day: str, subperiods: int) -> GridState:
    return GridState(sender=DMO, market_day=market_day, hour=1, subperiods=subperiods, connected=(True,) * subperiods)


def meter_report(grid: GridState) -> MeterReport:
    """The echo's answer to a GridState: a MeterReport of the same hour and size, with non-trivial floats."""
    k = grid.subperiods
    return MeterReport(sender=AGENT, market_day=grid.market_day, hour=grid.hour, subperiods=k,
                       p_m_mw=tuple(1.234567 + 0.1 * i for i in range(k)),
                       deviation_mw=tuple(-0.0123456 * (i + 1) for i in range(k)))


def codec_row(msg, iterations: int) -> dict:
    """Microseconds per encode and per decode (parse + validate against its kind) of one message."""
    payload = encode(msg)
    start = time.perf_counter()
    for _ in range(iterations):
        encode(msg)
    mid = time.perf_counter()
    for _ in range(iterations):
        decode(payload, expected_kind=msg.kind)
    end = time.perf_counter()
    return {"kind": msg.kind, "bytes": len(payload), "encode_us": (mid - start) / iterations * 1e6,
            "decode_us": (end - mid) / iterations * 1e6}


def round_trips(args, send, replies: queue.Queue, check) -> dict:
    """Send, wait for the echo on the main thread, repeat; statistics of the counted ones in milliseconds."""
    times = []
    for i in range(args.warmup + args.messages):
        start = time.perf_counter_ns()
        send(i)
        try:
            got = replies.get(timeout=TIMEOUT_S)
        except queue.Empty:
            raise RuntimeError(f"no echo of message {i} within {TIMEOUT_S:g} s") from None
        elapsed = time.perf_counter_ns() - start
        if not check(i, got):
            raise RuntimeError(f"echo of message {i} does not match it")
        if i >= args.warmup:
            times.append(elapsed / 1e6)
    ms = np.asarray(times)
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {"n": len(ms), "p50": float(p50), "p90": float(p90), "p99": float(p99), "mean": float(ms.mean()),
            "max": float(ms.max())}


class Counter:
    """Counts arrivals (from Zenoh's callback thread) and the monotonic times of the first and last."""

    def __init__(self):
        self.lock = threading.Lock()
        self.active = False
        self.count = 0
        self.first = self.last = 0

    def tick(self, _payload=None) -> None:
        now = time.monotonic_ns()
        with self.lock:
            self.count += 1
            self.first = self.first or now
            self.last = now

    def snapshot(self) -> tuple[int, int, int]:
        with self.lock:
            return self.count, self.first, self.last


def burst(echo: Echo, what: str, n: int, subperiods: int, counter: Counter) -> dict:
    """Have the echo process put ``n`` messages as fast as it can; count what arrives here until the sender is done
    and nothing more has come for half a second. Rates are from the sender's first put (monotonic clock, shared by
    the processes of one machine)."""
    counter.active = True
    sender = echo.command(what, n, subperiods)
    settled, seen = time.monotonic() + 4 * TIMEOUT_S, -1
    while time.monotonic() < settled:
        count = counter.snapshot()[0]
        if count >= n:
            break
        if count == seen:  # nothing new for half a second: the rest was dropped
            break
        seen = count
        time.sleep(0.5)
    count, _, last = counter.snapshot()
    counter.active = False
    t0, t1 = sender["t0"], sender["t1"]
    received_s = (last - t0) / 1e9 if count else float("nan")
    return {"sent": n, "received": count, "lost": n - count, "send_s": (t1 - t0) / 1e9,
            "sent_per_s": n / ((t1 - t0) / 1e9), "received_per_s": count / received_s if count else 0.0}


class Echo:
    """The echo process, started with pipes for its commands and stopped (quit, then SIGTERM, then SIGKILL) on exit."""

    def __init__(self, run_id: str, endpoint: str, market_day: str):
        self.argv = [sys.executable, "-m", "dmosim.bench.messaging", "--echo", "--run-id", run_id,
                     "--connect", endpoint, "--market-day", market_day]
        self.lines: queue.Queue = queue.Queue()
        self.process: subprocess.Popen | None = None

    def __enter__(self) -> Echo:
        try:
            with interrupts_held():  # recorded before a Ctrl-C can leave it running unseen
                self.process = subprocess.Popen(self.argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                                process_group=0, env=role_env())
            threading.Thread(target=self._read, daemon=True, name="echo-stdout").start()
            self._answer("ready")
        except BaseException:
            self.__exit__()
            raise
        return self

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.put(json.loads(line))
        self.lines.put(None)  # the process closed its stdout: it is gone

    def _answer(self, what: str) -> dict:
        try:
            answer = self.lines.get(timeout=TIMEOUT_S * 4)
        except queue.Empty:
            raise RuntimeError(f"the echo process did not answer {what!r}") from None
        if answer is None:
            raise RuntimeError(f"the echo process exited (code {self.process.wait()}) before answering {what!r}")
        return answer

    def command(self, what: str, *numbers: int) -> dict:
        self.process.stdin.write(" ".join([what, *map(str, numbers)]) + "\n")
        self.process.stdin.flush()
        return self._answer(what)

    def __exit__(self, *exc) -> None:
        process, self.process = self.process, None
        if process is None:
            return
        try:
            process.stdin.close()  # the echo process quits at the end of its input
            process.wait(timeout=QUIT_S)
        except (OSError, subprocess.TimeoutExpired):
            stop_processes([process], ROLE_STOP_S)


# --- the echo process --------------------------------------------------------------------------------------------

def echo_main(run_id: str, endpoint: str, market_day: str) -> None:
    """Answer each GridState with a MeterReport and each raw ping with a pong, on the main thread. On the command
    ``burst N K`` or ``raw N K`` (stdin), put N MeterReports of K sub-periods through the Bus, or N plain puts of
    their bytes, and print the monotonic times of the first and last put as one JSON line."""
    events: queue.Queue = queue.Queue()

    def read_commands() -> None:
        for line in sys.stdin:
            events.put(("command", line.split()))
        events.put(("command", ["quit"]))

    def say(obj: dict) -> None:
        print(json.dumps(obj), flush=True)

    with Bus(run_id, AGENT, BusConfig(mode="client", connect=(endpoint,))) as bus:
        raw = bus.keys.prefix + "/bench"
        with bus.subscribe(bus.keys.grid(), lambda key, msg, t: events.put(("grid", msg))), \
                bus.session.declare_subscriber(f"{raw}/ping", lambda s: events.put(("ping", s.payload.to_bytes()))), \
                bus.session.declare_publisher(f"{raw}/pong") as pong, \
                bus.session.declare_publisher(f"{raw}/burst") as raw_burst:
            for ok in (bus.wait_for_subscribers(bus.keys.meter(AGENT), TIMEOUT_S), wait_matching(pong, TIMEOUT_S),
                       wait_matching(raw_burst, TIMEOUT_S)):
                if not ok:
                    raise RuntimeError("the benchmark's subscribers did not show up")
            say({"ready": True})
            threading.Thread(target=read_commands, daemon=True, name="commands").start()
            while True:
                kind, item = events.get()
                if kind == "grid":
                    bus.publish(meter_report(item))
                elif kind == "ping":
                    pong.put(item)
                elif item[0] == "burst":
                    report = meter_report(grid_state(market_day, int(item[2])))
                    t0 = time.monotonic_ns()
                    for _ in range(int(item[1])):
                        bus.publish(report)
                    say({"t0": t0, "t1": time.monotonic_ns()})
                elif item[0] == "raw":
                    payload = encode(meter_report(grid_state(market_day, int(item[2]))))
                    t0 = time.monotonic_ns()
                    for _ in range(int(item[1])):
                        raw_burst.put(payload)
                    say({"t0": t0, "t1": time.monotonic_ns()})
                else:
                    return


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m dmosim.bench.messaging", description="the echo side of the bench")
    parser.add_argument("--echo", action="store_true", required=True)
    parser.add_argument("--run-id", required=True)
    parser.add_argument("--connect", required=True)
    parser.add_argument("--market-day", required=True)
    cli = parser.parse_args()
    echo_main(cli.run_id, cli.connect, cli.market_day)
