"""``--cluster`` without a cluster (docs/cluster.md): how agents are dealt to workers, when a task stops on its
lifeline, what the flag accepts, the check that workers see a directory, and the one-line errors of ``dmosim run``
and ``dmosim sweep`` (no Dask installed, a malformed address, a scheduler without dmosim's TLS certificates unless
``--insecure-cluster``, a scheduler nobody runs, a fault it cannot fire). A cluster over TLS is in
tests/dmosim/test_cluster_tls.py; runs on a real Dask cluster in tests/system/test_on_a_cluster.py."""

from __future__ import annotations

import datetime
import json
import re
import socket
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from dmosim.cli import main
from dmosim.launch import clusterauth
from dmosim.launch.clusterauth import client_security, create_cluster_auth
from messages.transport.access import AuthError
from dmosim.launch.cluster import CUT, INSTALL, Cluster, ClusterError, ClusterUsage, Tether, connect, deal, \
    read_token, scheduler_address
from dmosim.launch.processes import free_port

EXPERIMENT = 'name = "tiny"\n[agents]\ncount = 2\n'
OPEN = ("--cluster", "tcp://10.0.0.5:8786", "--insecure-cluster")  # a scheduler without TLS, allowed


def test_agents_are_dealt_to_the_workers_in_turn():
    assert deal(["mg1", "mg2", "mg3", "mg4", "mg5"], ["w1", "w2"]) == {"w1": ["mg1", "mg3", "mg5"], "w2": ["mg2", "mg4"]}
    assert deal(["mg1"], ["w1", "w2", "w3"]) == {"w1": ["mg1"]}  # a worker dealt nothing gets no task
    shares = deal([f"mg{i}" for i in range(1, 102)], [f"w{i}" for i in range(7)])
    assert sorted(n for share in shares.values() for n in share) == sorted(f"mg{i}" for i in range(1, 102))
    assert max(map(len, shares.values())) - min(map(len, shares.values())) == 1


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_task_stops_when_its_lifeline_is_cut_or_no_longer_beaten():
    clock, values = Clock(), iter([0, 1, 1, 2, 2, 2, 2])
    tether = Tether(lambda: next(values), clock, lost_after_s=60)
    for now in (0, 30, 89, 90, 149):  # a new beat at 0 and at 90; the same one in between, for less than 60 s
        clock.now = now
        assert not tether.cut()
    clock.now = 150.5  # 60.5 s without a new beat: the launcher is gone
    assert tether.cut()

    cut = Tether(iter([0, CUT]).__next__, Clock())
    assert not cut.cut() and cut.cut()


def test_a_lifeline_out_of_reach_counts_as_no_new_beat():
    clock = Clock()

    def unreachable():
        raise OSError("the scheduler is gone")

    tether = Tether(unreachable, clock, lost_after_s=60)
    clock.now = 59
    assert not tether.cut()
    clock.now = 61
    assert tether.cut()


@pytest.mark.parametrize("text, expected", [
    ("tcp://10.0.0.5:8786", ("tcp", "10.0.0.5", 8786)),
    ("10.0.0.5:8786", ("tcp", "10.0.0.5", 8786)),
    ("tls://sched.example.org:8786", ("tls", "sched.example.org", 8786)),
    ("tcp://[::1]:8786", ("tcp", "::1", 8786)),
])
def test_a_scheduler_address_is_read(text, expected):
    assert scheduler_address(text) == expected


@pytest.mark.parametrize("text", ["sched", "tcp://sched", "tcp://sched:0", "sched:99999", "ws://sched:8786",
                                  "tcp://:8786", "tcp://a b:8786", "no-such-file.json"])
def test_a_malformed_scheduler_address_is_refused(text):
    with pytest.raises(ClusterUsage, match="--cluster"):
        scheduler_address(text)


def test_a_scheduler_file_gives_its_address(tmp_path):
    (tmp_path / "scheduler.json").write_text(json.dumps({"type": "Scheduler", "address": "tcp://10.0.0.5:8786"}))
    assert scheduler_address(str(tmp_path / "scheduler.json")) == ("tcp", "10.0.0.5", 8786)
    (tmp_path / "other.json").write_text("[1, 2]")
    with pytest.raises(ClusterUsage, match="not a Dask scheduler file"):
        scheduler_address(str(tmp_path / "other.json"))


class Workers:
    """A client whose ``run`` calls the function here as each worker would: ``blind`` ones cannot read the file."""

    def __init__(self, blind: set[str] = frozenset()):
        self.blind = blind

    def run(self, function, *args):
        return {w: (None if w in self.blind else function(*args)) for w in ("tcp://w1:1", "tcp://w2:1")}


def test_every_worker_must_see_the_directory(tmp_path):
    Cluster(Workers(set()), "tcp://s:1", "127.0.0.1").check_sees(tmp_path)
    with pytest.raises(ClusterUsage, match=r"1 of the cluster's 2 workers do not see it \(tcp://w2:1"):
        Cluster(Workers({"tcp://w2:1"}), "tcp://s:1", "127.0.0.1").check_sees(tmp_path)
    assert list(tmp_path.iterdir()) == []  # the probe file is gone either way
    assert read_token(str(tmp_path / "missing")) is None


def test_every_worker_must_reach_the_dmo():
    with socket.socket() as listening:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        Cluster(Workers(), "tcp://s:1", "127.0.0.1").check_reaches(listening.getsockname()[1])
    port = free_port()
    with pytest.raises(ClusterError, match=rf"2 workers cannot reach this machine's DMO at 127.0.0.1:{port} "
                                           r"\(tcp://w1:1: Connection refused\); give --advertise"):
        Cluster(Workers(), "tcp://s:1", "127.0.0.1").check_reaches(port)


def test_a_scheduler_nobody_runs_is_a_runtime_failure():
    with pytest.raises(ClusterError, match="cannot reach the Dask scheduler at 127.0.0.1:"):
        connect(f"tcp://127.0.0.1:{free_port()}")


@pytest.fixture
def experiment(tmp_path) -> Path:
    (tmp_path / "tiny.toml").write_text(EXPERIMENT)
    return tmp_path / "tiny.toml"


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_the_flag_without_dask_names_the_extra_to_install(experiment, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if it were not installed
    assert main(["sweep", str(experiment), "--set", "seed=1,2", *OPEN, "--check"]) == 2
    assert INSTALL in one_line(capsys) and INSTALL == "pip install 'dmosim[cluster]'"
    assert main(["run", str(experiment), *OPEN, "--check"]) == 2
    assert INSTALL in one_line(capsys)


def test_run_refuses_what_it_cannot_do_on_a_cluster(experiment, capsys):
    assert main(["run", str(experiment), *OPEN, "--fault", "kill:mg2:3", "--check"]) == 2
    assert "--fault kill:mg2:3: with --cluster the agents run on the cluster's workers" in one_line(capsys)
    assert main(["run", str(experiment), *OPEN, "--fault", "restart:mg1:3", "--check"]) == 2
    one_line(capsys)
    assert main(["run", str(experiment), "--advertise", "10.0.0.1", "--check"]) == 2
    assert "--advertise goes with --cluster" in one_line(capsys)
    assert main(["run", str(experiment), *OPEN, "--advertise", "a b", "--check"]) == 2
    assert "--advertise 'a b'" in one_line(capsys)
    assert main(["run", str(experiment), "--cluster", "10.0.0.5", "--insecure-cluster", "--check"]) == 2
    assert "expected a scheduler's address" in one_line(capsys)
    assert main(["run", str(experiment), *OPEN, "--hosting", "fork", "--per-process", "4", "--check"]) == 2
    assert "agents.per_process = 4: with --cluster each worker forks its agents one to a process" in one_line(capsys)
    assert main(["run", str(experiment), *OPEN, "--routers", "2", "--check"]) == 2
    assert "agents.routers = 2: with --cluster the agents connect to the DMO from the workers" in one_line(capsys)
    # the DMO and the recorder stay on this machine: their faults are fired as ever
    assert main(["run", str(experiment), *OPEN, "--fault", "restart:dmo:3", "--fault", "kill:recorder:2",
                 "--check"]) == 0


def test_a_sweep_on_a_scheduler_nobody_runs_fails_in_one_line_and_leaves_nothing(experiment, tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["sweep", str(experiment), "--set", "seed=1,2", "--cluster", f"tcp://127.0.0.1:{free_port()}",
                 "--insecure-cluster", "--out", str(out)]) == 1
    assert "cannot reach the Dask scheduler" in one_line(capsys)
    assert not out.exists()


@pytest.mark.parametrize("verb", [["run"], ["sweep", "--set", "seed=1,2"]])
def test_a_scheduler_without_tls_is_refused_before_anything_starts_unless_the_user_says_so(verb, experiment, tmp_path,
                                                                                            capsys):
    (tmp_path / "scheduler.json").write_text(json.dumps({"type": "Scheduler", "address": "tcp://10.0.0.5:8786"}))
    out = tmp_path / "out"
    for address in ("tcp://10.0.0.5:8786", "10.0.0.5:8786", "tls://10.0.0.5:8786", str(tmp_path / "scheduler.json")):
        assert main([verb[0], str(experiment), *verb[1:], "--cluster", address, "--out", str(out)]) == 2
        assert f"--cluster {address}: a Dask scheduler's users can run any code on its workers" in one_line(capsys)
        assert not out.exists()  # refused before a directory is made or the scheduler reached
    for address in ("tcp://10.0.0.5:8786", "10.0.0.5:8786", str(tmp_path / "scheduler.json")):
        assert main([verb[0], str(experiment), *verb[1:], "--cluster", address, "--insecure-cluster", "--check"]) == 0
        capsys.readouterr()
    # a tls:// scheduler is reached with dmosim's certificates, never with none
    assert main([verb[0], str(experiment), *verb[1:], "--cluster", "tls://10.0.0.5:8786", "--insecure-cluster",
                 "--check"]) == 2
    assert "a tls:// scheduler is reached with --cluster-auth DIR" in one_line(capsys)


def test_the_cluster_flags_are_refused_where_they_do_not_fit(experiment, tmp_path, capsys):
    assert main(["credentials", "--cluster", "--out", str(tmp_path / "cluster")]) == 0
    capsys.readouterr()
    auth = str(tmp_path / "cluster")
    for flags, says in [
        (["--cluster-auth", auth], "--cluster-auth goes with --cluster"),
        (["--insecure-cluster"], "--insecure-cluster goes with --cluster"),
        (["--cluster", "tls://10.0.0.5:8786", "--cluster-auth", auth, "--insecure-cluster"],
         "--cluster-auth and --insecure-cluster exclude each other"),
        (["--cluster", "tcp://10.0.0.5:8786", "--cluster-auth", auth],
         "with --cluster-auth the scheduler is reached at tls://HOST:PORT"),
        (["--cluster", "tls://10.0.0.5:8786", "--cluster-auth", str(tmp_path / "none")],
         f"--cluster-auth {tmp_path / 'none'}: no such directory"),
    ]:
        assert main(["run", str(experiment), *flags, "--check"]) == 2, flags
        assert says in one_line(capsys), flags
    assert main(["run", str(experiment), "--cluster", "tls://10.0.0.5:8786", "--cluster-auth", auth, "--check"]) == 0


class Later(datetime.datetime):
    """The clock 31 days on: the certificates of `dmosim credentials --cluster` (30 days) have expired."""

    @classmethod
    def now(cls, tz=None):
        return super().now(tz) + datetime.timedelta(days=31)


@pytest.mark.parametrize("spoil, says", [
    (lambda auth: (auth / "client" / "key.pem").unlink(), r"client: holds no key.pem"),
    (lambda auth: (auth / "client" / "key.pem").chmod(0o644), r"client/key.pem is readable by others"),
    (lambda auth: (auth / "client" / "cert.pem").write_text("junk"), r"client: not a certificate and key"),
    (lambda auth: (auth / "worker").chmod(0o777), r"worker is writable by its group"),
])
def test_cluster_credentials_that_cannot_be_used_are_refused_in_one_line(tmp_path, capsys, spoil, says):
    experiment = tmp_path / "tiny.toml"
    experiment.write_text(EXPERIMENT)
    auth = tmp_path / "cluster"
    assert main(["credentials", "--cluster", "--out", str(auth)]) == 0
    capsys.readouterr()
    spoil(auth)
    assert main(["run", str(experiment), "--cluster", "tls://10.0.0.5:8786", "--cluster-auth", str(auth),
                 "--check"]) == 2
    assert re.search(says, one_line(capsys))


def test_expired_cluster_credentials_are_refused_in_one_line(tmp_path, monkeypatch):
    auth = create_cluster_auth(tmp_path / "cluster", 30)
    client_security(auth)
    monkeypatch.setattr(clusterauth, "dt", SimpleNamespace(datetime=Later, timezone=datetime.timezone))
    with pytest.raises(AuthError, match=r"client/cert.pem: valid from .* UTC, not now; make new credentials"):
        client_security(auth)
