"""``--cluster`` on a real Dask cluster of this machine (``distributed.LocalCluster``, two worker processes, over TLS
with the certificates of ``dmosim credentials --cluster``, always closed; docs/cluster.md). ``dmosim sweep
--cluster``: each variant's run is a task on the workers and settles to the cent as the same experiment run here.
``dmosim run --cluster --hosting fork``: the agents, forked on the workers and connected to the DMO where
``--advertise`` says, settle as that variant's run, whose agents were all on one host. No run directory holds the
run's credentials. An agent still running when the launcher lets go is stopped on its worker; a sweep stopped
(Ctrl-C) cancels what waits for a worker and stops what runs."""

from __future__ import annotations

import json
import os
import queue
import subprocess
import time
from pathlib import Path

import pandas as pd
import pytest
from test_market_day import ENV, ROOT, dmosim, ended

from dmo.replay.reproduce import differences
from dmosim.cli.main import main
from dmosim.launch.cluster import CANCELLED, Cluster, Commands, RemoteAgents
from dmosim.launch.clusterauth import cluster_security
from dmosim.launch.processes import free_port
from messages.keys import new_run_id
from messages.recording import read_recording
from messages.transport.credentials import SECRETS, create_auth_dir, read_bundle

distributed = pytest.importorskip("distributed")  # the test extra installs it; the cluster extra for users

EXPERIMENT = """name = "tiny"
market_day = "2026-07-01"
[agents]
count = 2
[market]
subperiods = 1
penalty = {penalty}
[schedule]
scenarios = 1
gap = 0.05
time_limit = 60.0
[deadlines]
registration = 60.0
bid = 120.0
schedule = 120.0
hour = 60.0
"""


@pytest.fixture(scope="module")
def auth(tmp_path_factory) -> Path:
    """The cluster's certificates, as a user makes them."""
    auth = tmp_path_factory.mktemp("cluster") / "auth"
    assert main(["credentials", "--cluster", "--out", str(auth)]) == 0
    return auth


@pytest.fixture(scope="module")
def cluster(auth):
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, protocol="tls://",
                                  host="127.0.0.1", scheduler_port=0, dashboard_address="127.0.0.1:0",
                                  worker_dashboard_address="127.0.0.1:0", security=cluster_security(auth)) as local, \
            distributed.Client(local, set_as_default=False) as client:
        client.get_task_stream()  # from now on the scheduler keeps a record of each task: where it ran
        yield client


def sweep_and_run_here(cluster, auth: Path, tmp: Path) -> tuple[dict, dict, str]:
    """A sweep of penalty 0 and 150 on the cluster, and beside it the same experiment at penalty 0 run here: the
    sweep's summary, the run's result, and the sweep's progress lines."""
    for penalty in (0, 150):
        (tmp / f"penalty-{penalty}.toml").write_text(EXPERIMENT.format(penalty=float(penalty)))
    runs = {"sweep": subprocess.Popen(dmosim("sweep", str(tmp / "penalty-0.toml"), "--set", "market.penalty=0,150",
                                             "--cluster", cluster.scheduler.address, "--cluster-auth", str(auth),
                                             "--out", str(tmp / "sweep"), "--json"),
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     cwd=ROOT, env=ENV),
            "here": subprocess.Popen(dmosim("run", str(tmp / "penalty-0.toml"), "--out", str(tmp / "here"), "--json",
                                            "--quiet"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     cwd=ROOT, env=ENV)}
    try:
        out = {name: p.communicate(timeout=900) for name, p in runs.items()}
    finally:
        for p in runs.values():
            if p.poll() is None:
                p.terminate()  # the sweep cancels its tasks and stops its runs, the run its roles
                p.wait()
    for name, p in runs.items():
        assert p.returncode == 0, f"{name}: {out[name][1][-3000:]}"
    return json.loads(out["sweep"][0]), json.loads(out["here"][0]), out["sweep"][1]


# One test, so that the runs it compares run once even when pytest-xdist deals the tests of this file to
# several processes.
def test_a_sweep_on_a_cluster_and_agents_forked_on_its_workers_settle_as_runs_on_one_host(cluster, auth, tmp_path):
    summary, here, progress = sweep_and_run_here(cluster, auth, tmp_path)
    assert f"2 run(s), 2 at a time on the cluster at {cluster.scheduler.address} (2 workers, 2 threads)" in progress
    # each variant was a task of the cluster's workers
    ran = {t["key"].rsplit("-", 1)[0]: t["worker"] for t in cluster.get_task_stream()
           if str(t["key"]).startswith("dmosim-sweep-")}
    table = pd.read_csv(summary["table"])
    assert set(ran) == {f"dmosim-sweep-{label}" for label in table["label"]}
    assert set(ran.values()) <= set(cluster.scheduler_info()["workers"])
    assert summary["failed"] == [] and summary["untrusted"] == [] and list(table["status"]) == ["ok"] * 4
    assert (tmp_path / "sweep" / "sweep.png").read_bytes()[:4] == b"\x89PNG"

    # the variant at penalty 0 settles to the cent as the same experiment run here
    first = table[table["market.penalty"] == 0].set_index("agent")
    for agent, statement in here["settlement"].items():
        for column in ("energy_charge", "deviation_penalty", "total"):
            assert first.loc[agent, column] == statement[column], (agent, column)
    assert differences(read_recording(here["recording"]),
                       read_recording(tmp_path / "sweep" / first["label"].iloc[0] / "recording.mcap")) == []

    # the variant at penalty 150 again, its agents forked on the two workers: settled as when all were on one host
    variant = table[table["market.penalty"] == 150]["label"].iloc[0]
    on_one_host = json.loads((tmp_path / "sweep" / variant / "result.json").read_text())
    out = ended(dmosim("run", str(tmp_path / "sweep" / "experiments" / f"{variant}.toml"), "--hosting",
                       "fork", "--cluster", cluster.scheduler.address, "--cluster-auth", str(auth),
                       "--advertise", "127.0.0.2", "--out", str(tmp_path / "run"), "--json", "--quiet"),
                timeout=600, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    spread = json.loads(out.stdout)
    assert spread["settlement"] == on_one_host["settlement"] and spread["awards"] == on_one_host["awards"]
    workers = sorted(cluster.scheduler_info()["workers"])
    assert spread["cluster"]["agents"] == {workers[0]: ["mg1"], workers[1]: ["mg2"]}
    assert spread["cluster"]["dmo"].startswith("tcp/127.0.0.2:")  # where --advertise said the workers reach it
    logs = tmp_path / "run" / "logs"
    for i, agent in enumerate(("mg1", "mg2"), start=1):  # each worker's host forked its agent, and their logs are here
        assert f" {agent} " in (logs / f"{agent}.log").read_text()  # its lines, each naming it
        assert (logs / f"_host-{i}.log").is_file()
    # the run's credentials were on this machine and the workers' own, never where every worker reads
    assert [p for p in tmp_path.rglob("*") if p.name in SECRETS or p.name == "auth"] == []


def test_an_agent_still_running_when_the_launcher_lets_go_is_stopped_on_its_worker(cluster, tmp_path, listener):
    run_id, log, exits = new_run_id(), tmp_path / "mg1.log", queue.Queue()
    credentials = create_auth_dir(tmp_path / "auth", run_id, ["mg1"])
    # an agent that waits, for ten minutes, for a DMO that never answers
    waits = ["agent", "--run-id", run_id, "--id", "mg1", "--connect", f"tcp/127.0.0.1:{listener.port}",
             "--connect-timeout", "600"]
    with RemoteAgents(Cluster(cluster, cluster.scheduler.address, "127.0.0.1"), run_id, exits) as remote:
        remote.start([("mg1", waits, log)], {"mg1": read_bundle(credentials, "mg1")}, None,
                     lambda i: tmp_path / "unused.log")
        listener.accept(timeout_s=300)  # it runs on its worker, trying to reach its DMO
    assert remote.stop() == {"mg1": -15}  # SIGTERM from its task, once the launcher cut the lifeline
    assert exits.get_nowait() == ("mg1", -15)
    assert _running(run_id) == []


def test_a_sweep_stopped_cancels_what_waits_and_stops_what_runs(cluster):
    run_id = new_run_id()
    waits = ["agent", "--run-id", run_id, "--id", "mg1", "--connect", f"tcp/127.0.0.1:{free_port()}",
             "--connect-timeout", "600", "--insecure"]
    commands = Commands(Cluster(cluster, cluster.scheduler.address, "127.0.0.1"))
    polls = [commands.start(waits, f"dmosim-test-{i}") for i in range(3)]  # two workers of one thread: one waits
    deadline = time.monotonic() + 300
    while len(_running(run_id)) < 2:
        assert time.monotonic() < deadline, "the commands never started"
        time.sleep(0.1)  # paces the look at /proc: nothing to wait on but the processes appearing
    commands.stop()
    ended = [poll() for poll in polls]
    assert sorted(code for code, _, _ in ended) == [-15, -15, 1]  # two stopped by SIGTERM, and one that never ran:
    assert (1, "", CANCELLED) in ended
    assert _running(run_id) == []


def _running(run_id: str) -> list[str]:
    """The processes of this machine that have ``run_id`` on their command line."""
    return [pid for pid in os.listdir("/proc") if pid.isdigit() and run_id in _cmdline(pid)]


def _cmdline(pid: str) -> str:
    try:
        return open(f"/proc/{pid}/cmdline", "rb").read().decode(errors="replace")
    except OSError:
        return ""
