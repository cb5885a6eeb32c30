"""A network partition, and the roles across hosts: the DMO and each agent in its own network namespace, joined by
veth pairs on a bridge in the DMO's namespace (docs/faults.md). One agent's link goes down mid-day and comes back;
the day completes, the outage is in the incidents, and the agent catches up and reports again.

Needs root and iproute2 (CI runs as root); skipped otherwise. Names are unique per run, and the namespaces (with
their links and the bridge) are deleted in a ``finally``, after every process in them is stopped.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import subprocess
import sys
import time

import pytest

from dmosim.launch.processes import Roles
from messages.keys import new_run_id
from messages.transport.credentials import create_auth_dir
from test_market_day import DAY, DEADLINES, ENV, TINY

pytestmark = pytest.mark.skipif(not (hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("ip")),
                                reason="needs root and iproute2 (ip netns)")

SUBNET = "10.77.0"
PORT = 7447


def ip(*args: str) -> None:
    out = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if out.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {out.stderr.strip()}")


@contextlib.contextmanager
def hosts(agents: tuple[str, ...]):
    """One namespace for the DMO (with a bridge at SUBNET.1) and one per agent (SUBNET.2, .3, ...), each agent's
    veth pair enslaved to the bridge. Yields (namespace of the DMO, {agent: (namespace, its link)})."""
    tag = "dm" + secrets.token_hex(3)
    dmo_ns = f"{tag}-dmo"
    made: list[str] = []
    try:
        for ns in [dmo_ns, *(f"{tag}-{a}" for a in agents)]:
            ip("netns", "add", ns)
            made.append(ns)
            ip("-n", ns, "link", "set", "lo", "up")
        ip("-n", dmo_ns, "link", "add", "br0", "type", "bridge")
        ip("-n", dmo_ns, "addr", "add", f"{SUBNET}.1/24", "dev", "br0")
        ip("-n", dmo_ns, "link", "set", "br0", "up")
        links = {}
        for i, agent in enumerate(agents, start=1):
            ns, near, far = f"{tag}-{agent}", f"{tag}h{i}", f"{tag}a{i}"
            ip("link", "add", near, "netns", dmo_ns, "type", "veth", "peer", "name", far, "netns", ns)
            ip("-n", dmo_ns, "link", "set", near, "master", "br0", "up")
            ip("-n", ns, "addr", "add", f"{SUBNET}.{i + 1}/24", "dev", far)
            ip("-n", ns, "link", "set", far, "up")
            links[agent] = (ns, far)
        yield dmo_ns, links
    finally:
        for ns in made:  # deleting a namespace deletes its links, the bridge and the veth peers
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)


def in_ns(ns: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "dmosim", *args]


# What the DMO's namespace hears of the day, written a line at a time to a FIFO: the clock (from the one said before
# it joined, "registration 0", to "realtime 4" and on) and each process of the run that joins or leaves ("left mg2"),
# as the DMO hears them (it is their router). A reader of the run's own: argv is the run id, the DMO's endpoint, the
# credentials and the FIFO.
WATCH = """
import sys, threading
from messages import decode
from messages.transport import Bus, BusConfig
from messages.transport.access import bundle_settings
run_id, endpoint, auth, fifo = sys.argv[1:]
said, lock = open(fifo, "w", buffering=1), threading.Lock()
def say(line):
    with lock:
        said.write(line + "\\n")
config = BusConfig(mode="client", connect=(endpoint,), connect_timeout_s=60, overrides=bundle_settings(auth, "watch"))
with Bus(run_id, "watch", config, announce=False) as bus:
    tell = lambda clock: say(f"{clock.phase} {clock.hour or 0}")
    bus.subscribe(bus.keys.clock(), lambda key, clock, at: tell(clock))
    for _, payload, _ in bus.fetch(bus.keys.clock()):  # the clock said before this joined
        tell(decode(payload))
    bus.watch_presence(lambda name: say(f"joined {name}"), lambda name: say(f"left {name}"))
    threading.Event().wait()
"""


def heard(fifo, watcher: int, line: str, timeout_s: float) -> None:
    """Read what the watcher says until it says ``line``."""
    deadline = time.monotonic() + timeout_s
    while fifo.line(watcher, max(0.0, deadline - time.monotonic())) != line:
        pass


def test_an_agent_cut_off_mid_day_comes_back_and_the_day_completes_across_hosts(tmp_path, fifo):
    agents = ("mg1", "mg2")
    run_id = new_run_id()
    endpoint = f"tcp/{SUBNET}.1:{PORT}"
    common = ["--run-id", run_id, "--market-day", DAY]
    result_path = tmp_path / "result.json"
    auth = create_auth_dir(tmp_path / "auth", run_id, list(agents), readers=("recorder", "watch"), dmo_client=False)
    with hosts(agents) as (dmo_ns, links), Roles() as roles:
        roles.start("dmo", in_ns(dmo_ns, "dmo", *common, "--listen", endpoint, "--agents", str(len(agents)),
                                 "--auth-dir", str(auth),
                                 "--subperiods", "1", "--result", str(result_path), "--lease", "2", *DEADLINES,
                                 # paces the hours (mg1 alone runs one in a fraction of a second), so the outage
                                 # spans a few hours rather than the rest of the day
                                 "--fault", "delay:dmo/grid:0.4"),
                    log=tmp_path / "dmo.log", env=ENV)
        watcher = roles.start("watch", ["ip", "netns", "exec", dmo_ns, sys.executable, "-c", WATCH, run_id, endpoint,
                                        str(auth), str(fifo.path)], log=tmp_path / "watch.log", env=ENV).process.pid
        heard(fifo, watcher, "registration 0", 60)
        for i, agent in enumerate(agents):
            roles.start(agent, in_ns(links[agent][0], "agent", *common, "--id", agent, "--connect", endpoint,
                                     "--seed", str(i), "--lease", "1", "--auth-dir", str(auth), *TINY),
                        log=tmp_path / f"{agent}.log", env=ENV)

        ns, link = links["mg2"]
        heard(fifo, watcher, "realtime 4", 300)
        ip("-n", ns, "link", "set", link, "down")
        down_at = time.monotonic()
        heard(fifo, watcher, "left mg2", 30)  # its lease (1 s) is over: gone for the DMO too
        time.sleep(max(0.0, 3.0 - (time.monotonic() - down_at)))  # an outage of 3 s at least
        ip("-n", ns, "link", "set", link, "up")
        heard(fifo, watcher, "joined mg2", 60)

        for name in ("dmo", *agents):
            code = roles.roles[name].process.wait(timeout=300)
            assert code == 0, f"{name} exited {code}:\n" + (tmp_path / f"{name}.log").read_text()[-3000:]
    result = json.loads(result_path.read_text())

    incidents = [i for i in result["incidents"] if i["agent"] == "mg2"]
    vanished = [i for i in incidents if "vanished (liveliness lost)" in i["reason"]]
    back = [i for i in incidents if i["reason"].startswith("reappeared after vanishing")]
    assert vanished and back and vanished[0]["hour"] >= 4 and back[0]["hour"] > vanished[0]["hour"]
    # mg2 missed the hours of the outage, no more, and reported again once back; mg1 missed nothing
    missing = result["settlement"]["mg2"]["missing_subperiods"]
    assert 1 <= missing <= back[0]["hour"] - vanished[0]["hour"] + 1
    assert result["settlement"]["mg1"]["missing_subperiods"] == 0
    assert result["accepted_messages"]["meter_report"] == 2 * 24 - missing
    # mg2 operated the hours whose grid state never reached it, unreported: its day, as it tells it, ran to its end,
    # and the hours it took a grid state for are exactly those it reported
    day = result["realised"]["mg2"][-1]
    assert len({e["hour"] for e in day["compute"] if e["kind"] == "grid_state"}) == 24 - missing
    print(f"\npartition: mg2 cut off at hour {vanished[0]['hour']}, back at hour {back[0]['hour']}; "
          f"{missing} hour(s) settled as missing; the day completed")
