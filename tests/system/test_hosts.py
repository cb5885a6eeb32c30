"""A fleet across hosts (docs/hosts.md): three routers on loopback, each standing for a host's, joined into a mesh
with the run's credentials, mutual TLS and access control at every router. The DMO and the recorder are clients of
host 1's router, mg1 of host 2's, mg2 of host 3's, whose router reaches host 1 only through host 2's. Host 3's
router dies mid-day: mg2 is settled as missing from then on, mg1 goes on, and the recording re-settles to the cent.

Every process is stopped by ``Roles`` whatever happens, on free ports and under a fresh run id.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import threading
import time

import zenoh

from dmosim.launch.mesh import MeshLinks
from dmosim.launch.processes import Roles, free_port, wait_listening
from messages import decode, new_run_id
from messages.keys import Keys
from messages.recording import read_recording
from messages.transport import BusConfig
from messages.transport.access import bundle_settings
from messages.transport.credentials import create_auth_dir
from test_market_day import DAY, DEADLINES, ENV, ROOT, TINY, dmosim, ended

HOSTS = ("r1", "r2", "r3")  # host 1's router serves the DMO and the recorder; r2 and r3 log in with their bundles
UPSTREAM = {"r2": "r1", "r3": "r2"}  # a chain: host 3 reaches host 1 through host 2's router
AGENTS = {"mg1": "r2", "mg2": "r3"}


def test_a_day_across_three_hosts_routers_settles_and_outlives_one_of_them(tmp_path):
    run_id = new_run_id()
    at = {host: f"tls/127.0.0.1:{free_port()}" for host in HOSTS}
    auth = create_auth_dir(tmp_path / "auth", run_id, list(AGENTS), tls=True, routers=tuple(UPSTREAM))
    common = ["--run-id", run_id, "--market-day", DAY]
    result_path, recording = tmp_path / "result.json", tmp_path / "day.mcap"
    log = {name: tmp_path / f"{name}.log" for name in (*HOSTS, "dmo", "recorder", *AGENTS)}
    with Roles() as roles, contextlib.ExitStack() as stack:
        alive = lambda name: (lambda: roles.roles[name].process.poll() is None)  # noqa: E731
        for host in HOSTS:
            relay = ["--user", host, "--connect", at[UPSTREAM[host]]] if host in UPSTREAM else []
            roles.start(host, dmosim("router", "--run-id", run_id, "--auth-dir", str(auth), "--listen", at[host],
                                     *relay), log=log[host], env=ENV)  # all at once: a router retries its --connect
        for host in HOSTS:
            wait_listening(int(at[host].rsplit(":", 1)[1]), 60, alive(host))
        mesh = MeshLinks(at["r1"], run_id, auth)  # the links as host 1's router sees them, all day
        stack.enter_context(mesh)
        # each end of both links holds a token for it, and host 3's reach host 1 only through host 2's
        mesh.wait(lambda up: len(up) == 2 * len(UPSTREAM), 60, lambda: all(alive(host)() for host in HOSTS))
        roles.start("dmo", dmosim("dmo", *common, "--mode", "client", "--connect", at["r1"], "--auth-dir", str(auth),
                                  "--agents", str(len(AGENTS)), "--subperiods", "1", "--result", str(result_path),
                                  "--await-recorder", "60", *DEADLINES), log=log["dmo"], env=ENV)
        roles.start("recorder", dmosim("record", "--run-id", run_id, "--out", str(recording), "--connect", at["r1"],
                                       "--auth-dir", str(auth)), log=log["recorder"], env=ENV)
        with Spy(run_id, at["r3"], auth) as spy:  # mg1's credentials, tried on host 3's router
            assert spy.clock_answered(120), log["dmo"].read_text()[-3000:]
            r3 = spy.router
            spy.forge()
            for i, (agent, host) in enumerate(AGENTS.items()):
                # Zenoh's lease (10 s): the link a killed router closes is seen at once, and a process starved of
                # the CPU on a loaded machine is not taken for gone
                roles.start(agent, dmosim("agent", *common, "--id", agent, "--connect", at[host], "--seed", str(i),
                                          "--auth-dir", str(auth), *TINY), log=log[agent], env=ENV)
            assert spy.hour_began(4, 600), log["dmo"].read_text()[-3000:]
        roles.kill("r3")
        assert roles.roles["dmo"].process.wait(timeout=300) == 0, log["dmo"].read_text()[-3000:]
        assert roles.roles["mg1"].process.wait(timeout=120) == 0, log["mg1"].read_text()[-3000:]
        roles.roles["recorder"].process.send_signal(signal.SIGTERM)
        assert roles.roles["recorder"].process.wait(timeout=60) == 0, log["recorder"].read_text()[-2000:]
    result = json.loads(result_path.read_text())

    # host 3's router reached host 1 through host 2's only, all day: routers do not find one another unasked
    links = {frozenset(link) for link in mesh.ever}
    (r2,) = set().union(*links) - {mesh.router, r3}
    assert links == {frozenset((mesh.router, r2)), frozenset((r2, r3))}
    # mg2 registered, bid, was awarded and reported across two routers' hops, until its host's router died
    rec = read_recording(str(recording))
    reported = {msg.sender: set() for _, msg in rec.decoded("registration")}
    for _, msg in rec.decoded("meter_report"):
        reported[msg.sender].add(msg.hour)
    assert set(reported) == set(AGENTS) and {msg.agent for _, msg in rec.decoded("award")} == set(AGENTS)
    assert reported["mg1"] == set(range(1, 25))
    assert 3 <= len(reported["mg2"]) < 24 and reported["mg2"] == set(range(1, len(reported["mg2"]) + 1))
    (vanished,) = [i for i in result["incidents"] if i["agent"] == "mg2" and "vanished" in i["reason"]]
    assert vanished["hour"] >= 4 and not [i for i in result["incidents"] if i["agent"] == "mg1"]
    settlement = result["settlement"]
    assert settlement["mg1"]["missing_subperiods"] == 0
    assert settlement["mg2"]["missing_subperiods"] == 24 - len(reported["mg2"])
    # what mg1's credentials tried on host 3's router went nowhere (the DMO refuses and counts any bid it is not
    # sent by mg2's own process), though they heard what they may hear
    assert spy.heard == [] and result["rejected_messages"] == 0

    settled = json.loads(subprocess.run(dmosim("settle", str(recording), "--json"), capture_output=True, text=True,
                                        timeout=300, cwd=ROOT, env=ENV).stdout)
    assert settled["identical"], settled
    assert settled["totals"] == {agent: s["total"] for agent, s in settlement.items()}
    print(f"\nmesh: 3 routers, mg2's router killed at hour {vanished['hour']}; mg2 settled with "
          f"{settlement['mg2']['missing_subperiods']} missing hour(s), mg1 with none; re-settled identically")


class Spy:
    """A session with mg1's credentials on host 3's router (``router``, its Zenoh id): it asks the DMO for its clock
    (which mg1 may, so it knows its session works through the mesh; the clock published as registration opened may
    have gone out before the session was up) and follows it, listens to mg2's award, and puts a bid on mg2's key."""

    def __init__(self, run_id: str, endpoint: str, auth):
        self.keys = Keys(run_id)
        self.config = BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, "mg1"))
        self.heard: list[str] = []
        self.hours: set[int] = set()  # the real-time hours whose clock it has heard
        self._clock = threading.Condition()

    def __enter__(self) -> Spy:
        self.session = zenoh.open(self.config.to_zenoh())
        self.router = str(self.session.info.routers_zid()[0])
        self.session.declare_subscriber(f"{self.keys.prefix}/dmo/award/mg2",
                                        lambda sample: self.heard.append(str(sample.key_expr)))
        self.session.declare_subscriber(self.keys.clock(), self._tick)
        return self

    def _tick(self, sample) -> None:
        clock = decode(sample.payload.to_bytes())
        with self._clock:
            if clock.phase == "realtime":
                self.hours.add(clock.hour)
            self._clock.notify_all()

    def hour_began(self, hour: int, timeout_s: float) -> bool:
        """Whether the DMO's clock says real-time ``hour`` has begun within ``timeout_s``."""
        with self._clock:
            return self._clock.wait_for(lambda: hour in self.hours, timeout_s)

    def clock_answered(self, timeout_s: float) -> bool:
        """Whether the DMO answers a query for its clock within ``timeout_s`` (asked again every 2 s)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if any(reply.ok is not None for reply in self.session.get(self.keys.clock(), timeout=2.0)):
                return True
            time.sleep(0.2)  # paces the questions while no route to the DMO's answers exists yet
        return False

    def forge(self) -> None:
        self.session.put(f"{self.keys.prefix}/agent/mg2/bid", json.dumps({"kind": "bid", "sender": "mg2"}).encode())

    def __exit__(self, *exc) -> None:
        self.session.close()


def test_dmosim_run_starts_a_router_per_simulated_host_and_spreads_the_agents_over_them(tmp_path):
    """``dmosim run --routers 2``: two routers in a mesh over mutual TLS, the DMO and the recorder clients of the
    first, mg1 and mg2 of the first and mg3 of the second; the day settles, and re-settles from its recording (the
    run's verdict), with no agent lost on the way."""
    argv = dmosim("run", "--agents", "3", "--routers", "2", "--subperiods", "1", *TINY, *DEADLINES, "--seed", "3",
                  "--out", str(tmp_path / "run"), "--json", "--quiet")
    out = ended(argv, timeout=600, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert result["verdict"]["ok"] and result["recorded"]["resettled"]["identical"]
    assert result["incidents"] == [] and set(result["settlement"]) == {"mg1", "mg2", "mg3"}
    # host2's link to host1 was up before the DMO started: the run waits for its token (dmosim/launch/mesh.py)
    routers = result["routers"]
    assert routers["roles"] == {"dmo": "host1", "recorder": "host1", "mg1": "host1", "mg2": "host1", "mg3": "host2"}
    assert len(set(routers["endpoints"].values())) == 2 and all(
        at.startswith("tls/127.0.0.1:") for at in routers["endpoints"].values())
