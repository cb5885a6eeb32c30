"""``--cluster`` over TLS (docs/cluster.md) on a ``distributed.LocalCluster`` of one worker, started with the
certificates ``dmosim credentials --cluster`` makes and always closed: dmosim's launcher connects with its bundle and
runs a command on the worker as ``sweep --cluster`` does; a client without the cluster's certificates reaches neither
the scheduler nor the worker; and an agent placed on the worker as ``run --cluster`` places it gets its own bundle
of the run's credentials, in a private directory there, and nothing else. An open scheduler (tcp://) is used only
with --insecure-cluster. Whole runs on a cluster are in tests/system/test_on_a_cluster.py.

What runs commands on the worker needs its worker to be a process, and is slow; who may connect is checked on a
cluster whose scheduler and worker are threads of this process."""

from __future__ import annotations

import asyncio
import os
import queue
import ssl
import stat
import time
from pathlib import Path

import pytest

from dmosim.cli.main import build_parser, main
from dmosim.console import UsageError
from dmosim.cli.placement import check_cluster, check_shared, connected
from dmosim.launch.cluster import Commands, RemoteAgents
from dmosim.launch.clusterauth import CLIENT, cluster_security
from dmosim.launch.processes import free_port
from messages.keys import new_run_id
from messages.transport.access import CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE
from messages.transport.credentials import create_auth_dir, read_bundle

distributed = pytest.importorskip("distributed")  # the test extra installs it; the cluster extra for users


def tls_cluster_of(tmp_path_factory, processes: bool):
    """A LocalCluster of one worker (a process, or a thread of this one) on loopback over TLS with dmosim's
    certificates (ports the OS picks); its credentials directory and its client."""
    auth = tmp_path_factory.mktemp("cluster") / "auth"
    assert main(["credentials", "--cluster", "--out", str(auth)]) == 0
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=processes, protocol="tls://",
                                  host="127.0.0.1", scheduler_port=0, dashboard_address="127.0.0.1:0",
                                  worker_dashboard_address="127.0.0.1:0", security=cluster_security(auth)) as local, \
            distributed.Client(local, set_as_default=False) as client:
        yield auth, client


@pytest.fixture(scope="module")
def tls_cluster(tmp_path_factory):
    """``tls_cluster_of`` a worker process."""
    yield from tls_cluster_of(tmp_path_factory, processes=True)


@pytest.fixture(scope="module")
def tls_cluster_here(tmp_path_factory):
    """``tls_cluster_of`` a worker thread of this process."""
    yield from tls_cluster_of(tmp_path_factory, processes=False)


def args_of(verb: list[str], *flags: str):
    return build_parser(verb[0]).parse_args([*verb, *flags])


@pytest.mark.slow
def test_the_launcher_connects_with_its_bundle_and_runs_a_command_on_a_worker(tls_cluster, tmp_path):
    auth, client = tls_cluster
    address = client.scheduler.address
    assert address.startswith("tls://127.0.0.1:")
    args = args_of(["sweep", "x.toml", "--set", "seed=1,2"], "--cluster", address, "--cluster-auth", str(auth))
    check_cluster(args)
    with connected(args) as cluster:
        assert cluster.workers() == sorted(client.scheduler_info()["workers"])
        check_shared(cluster, tmp_path)  # a task on the worker reads a file made here
        commands = Commands(cluster)  # what `dmosim sweep --cluster` runs each variant by
        try:
            poll = commands.start(["--version"], "dmosim-test-version")
            deadline = time.monotonic() + 120
            while (ended := poll()) is None:
                assert time.monotonic() < deadline, "the command never ended"
                time.sleep(0.1)  # paces the polls of a future, as the sweep does
        finally:
            commands.stop()
    code, out, err = ended
    assert code == 0, err
    assert out.startswith("dmosim ")


async def refused(address: str, context: ssl.SSLContext | None) -> Exception:
    """What a Dask connection to ``address`` over ``context`` (None: plain TCP) ends with: it must not open."""
    from distributed.comm import connect  # noqa: PLC0415

    rest = address.split("://")[1]
    try:
        comm = await connect(f"{'tls' if context else 'tcp'}://{rest}", timeout=10, ssl_context=context)
        await comm.read()  # the peer's handshake: a peer that accepted the connection answers
    except Exception as exc:  # noqa: BLE001  (refused: the point of the test)
        return exc
    raise AssertionError(f"{address} accepted a client without the cluster's certificates")


def stranger(certificates: Path | None) -> ssl.SSLContext:
    """A TLS client that trusts any server and presents ``certificates`` (a bundle of another CA), or none."""
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    if certificates:
        context.load_cert_chain(certificates / CERT_FILE, certificates / KEY_FILE)
    return context


def test_a_client_without_the_cluster_certificates_reaches_neither_scheduler_nor_worker(tls_cluster_here, tmp_path,
                                                                                       capsys):
    auth, client = tls_cluster_here
    assert main(["credentials", "--cluster", "--out", str(tmp_path / "other")]) == 0  # another cluster's
    capsys.readouterr()
    for address in [client.scheduler.address, *client.scheduler_info()["workers"]]:
        for context in (None, stranger(None), stranger(tmp_path / "other" / CLIENT)):
            assert isinstance(asyncio.run(refused(address, context)), OSError)  # Dask's CommClosedError is one
    # dmosim, given another cluster's certificates, says so in one line
    experiment = tmp_path / "tiny.toml"
    experiment.write_text('name = "tiny"\n[agents]\ncount = 2\n')
    assert main(["run", str(experiment), "--cluster", client.scheduler.address, "--cluster-auth",
                 str(tmp_path / "other"), "--out", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "TLS with the scheduler failed" in err, err
    assert not (tmp_path / "run").exists()
    # with the cluster's own, it connects
    with connected(args_of(["run"], "--cluster", client.scheduler.address, "--cluster-auth", str(auth))) as cluster:
        assert cluster.threads() == 2


@pytest.mark.slow
def test_an_agent_on_a_worker_gets_its_own_bundle_only_and_only_while_it_runs(tls_cluster, tmp_path):
    auth, client = tls_cluster
    run_id = new_run_id()
    credentials = create_auth_dir(tmp_path / "run-auth", run_id, ["mg1", "mg2"], readers=("recorder",), tls=True)
    # mg1, waiting for a DMO nobody runs, placed as `dmosim run --cluster` places it
    waits = ["agent", "--run-id", run_id, "--id", "mg1", "--connect", f"tcp/127.0.0.1:{free_port()}",
             "--connect-timeout", "600"]
    address = client.scheduler.address
    with connected(args_of(["run"], "--cluster", address, "--cluster-auth", str(auth))) as cluster, \
            RemoteAgents(cluster, run_id, queue.Queue()) as remote:
        remote.start([("mg1", waits, tmp_path / "mg1.log")], {"mg1": read_bundle(credentials, "mg1")}, None,
                     lambda i: tmp_path / "unused.log")
        given = _auth_dir_of(run_id)
        seen = {str(p.relative_to(given)): stat.S_IMODE(p.stat().st_mode) for p in [given, *given.rglob("*")]}
        assert seen == {".": 0o700, "mg1": 0o700, f"mg1/{PASSWORD_FILE}": 0o600, f"mg1/{KEY_FILE}": 0o600,
                        f"mg1/{CERT_FILE}": 0o644, f"mg1/{CA_FILE}": 0o644}
        assert read_bundle(given, "mg1") == read_bundle(credentials, "mg1")
        assert not given.is_relative_to(tmp_path)  # the worker's own, not the launcher's nor a shared one
        assert remote.stop() == {"mg1": -15}  # SIGTERM from its task, once the launcher cut the lifeline
    assert not given.exists()  # gone with the agent


def _auth_dir_of(run_id: str, timeout_s: float = 120) -> Path:
    """The ``--auth-dir`` of the agent process of ``run_id`` on this machine, once it has started and its bundle is
    there."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
            except OSError:
                continue
            if run_id in argv and "--auth-dir" in argv:
                given = Path(argv[argv.index("--auth-dir") + 1])
                if (given / "mg1" / PASSWORD_FILE).is_file():
                    return given
        time.sleep(0.1)  # paces the look at /proc: nothing to wait on but the process appearing
    raise AssertionError(f"no agent of run {run_id} started")


def test_an_open_scheduler_is_used_when_the_user_says_so():
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", scheduler_port=0, dashboard_address="127.0.0.1:0",
                                  worker_dashboard_address="127.0.0.1:0") as local:
        address = local.scheduler.address
        with pytest.raises(UsageError, match=f"--cluster {address}: a Dask scheduler's users can run any code"):
            check_cluster(args_of(["run"], "--cluster", address))
        args = args_of(["run"], "--cluster", address, "--insecure-cluster")
        check_cluster(args)
        with connected(args) as cluster:
            assert cluster.threads() == 1
