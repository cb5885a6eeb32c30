"""Processes of a sweep or a run placed on a Dask cluster (``--cluster``, docs/cluster.md): the launcher's connection
to the scheduler, the check that the workers see a directory, and the two tasks the workers run: one ``dmosim``
command (``dmosim sweep --cluster``: a variant's ``dmosim run``) and a share of a run's agents (``dmosim run
--cluster``), each in its own process group, as ``Roles`` starts them on this machine.

A running Dask task cannot be interrupted, so each task watches a lifeline, a ``distributed.Variable`` that the
launcher beats every ``BEAT_S``: once the launcher cuts it (the sweep or the run is over, failed or interrupted), or
stops beating it for ``LOST_AFTER_S`` (the launcher died), the task stops its processes (SIGTERM, SIGKILL after a
grace) and returns. Dask is imported only here and only when ``--cluster`` is given: it is an extra
(``pip install 'dmosim[cluster]'``).

The launcher reaches the scheduler over mutual TLS with the certificates of clusterauth.py (``--cluster-auth``), or
with none only when the user says so (``--insecure-cluster``, dmosim/cli/placement.py). The agents of ``dmosim run
--cluster`` get their credentials with their task, each its own bundle and nothing of the run's other ones; a task
keeps them in a private directory of its worker while its agents run.
"""

from __future__ import annotations

import json
import os
import queue
import secrets
import signal
import socket
import ssl
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from messages.transport.credentials import write_bundle

from .processes import COMMAND_STOP_S, ROLE_STOP_S, Command, Roles, dmosim_command, role_env, stop_processes

INSTALL = "pip install 'dmosim[cluster]'"
SCHEMES = ("tcp", "tls")  # the Dask transports a scheduler is reached by here (tcp only with --insecure-cluster)
CONNECT_TIMEOUT_S = 20.0  # how long the launcher tries to reach the scheduler
WORKERS_TIMEOUT_S = 60.0  # how long a cluster with no worker yet (batch jobs still in the queue) is waited for
REACH_TIMEOUT_S = 10.0  # how long a worker tries to open a connection to this machine's DMO
MAX_SCHEDULER_FILE = 65536  # bytes of a scheduler file (dask scheduler --scheduler-file writes about 300)
BEAT_S = 2.0  # the launcher's beat on a lifeline
LOST_AFTER_S = 60.0  # a lifeline not beaten for this long: the launcher is gone, and the task stops its processes
TASK_POLL_S = 1.0  # how often a task looks at its lifeline (and at its processes)
CUT = "cut"  # the lifeline's value once the launcher has cut it; before, the number of its beats
CANCELLED = "cancelled before it started"  # a command's error when it was stopped before its process started


class ClusterError(RuntimeError):
    """The cluster cannot be used now (its scheduler does not answer, it has no worker, a worker cannot reach this
    machine's DMO): a runtime failure, exit 1."""


class ClusterUsage(ValueError):
    """``--cluster`` cannot be used as given (no Dask installed, a malformed address, a directory the workers do not
    see): bad input, exit 2."""


@dataclass
class Cluster:
    """The launcher's connection to a Dask scheduler: ``address`` as the user named it, ``host`` the address of this
    machine that the workers reach it at (the DMO's endpoint of ``dmosim run --cluster``)."""

    client: object  # distributed.Client
    address: str
    host: str

    def workers(self) -> list[str]:
        """The workers' addresses, sorted: the order agents are dealt to them."""
        return sorted(self.client.scheduler_info()["workers"])

    def threads(self) -> int:
        """Tasks the workers run at once, in all."""
        return sum(self.client.nthreads().values())

    def check_sees(self, directory: Path) -> None:
        """``ClusterUsage`` unless every worker sees ``directory`` as this machine does: a file made here with a
        fresh token is read there (a shared filesystem, docs/cluster.md)."""
        directory = directory.resolve()
        probe = directory / f".cluster-probe-{secrets.token_hex(4)}"
        token = secrets.token_hex(16)
        probe.write_text(token)
        try:
            seen = self.client.run(read_token, str(probe))
        finally:
            probe.unlink()
        blind = sorted(w for w, text in seen.items() if text != token)
        if blind:
            raise ClusterUsage(f"{directory}: {len(blind)} of the cluster's {len(seen)} workers do not see it "
                               f"({blind[0]}...): the directory must be on a filesystem every worker shares "
                               "(docs/cluster.md)")

    def check_reaches(self, port: int) -> None:
        """``ClusterError`` unless every worker can open a TCP connection to this machine's ``host`` at ``port``
        (the DMO's), so that a wrong ``--advertise`` is told at once, not by agents that time out."""
        answers = self.client.run(reaches, self.host, port)
        cut = {w: why for w, why in sorted(answers.items()) if why is not None}
        if cut:
            worker, why = next(iter(cut.items()))
            raise ClusterError(f"{len(cut)} of the cluster's {len(answers)} workers cannot reach this machine's DMO at "
                               f"{_join(self.host, port)} ({worker}: {why}); give --advertise the address they reach "
                               "this machine at (docs/cluster.md)")

    def close(self) -> None:
        self.client.close()

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def connect(address: str, advertise: str | None = None, timeout_s: float = CONNECT_TIMEOUT_S,
            security=None) -> Cluster:
    """Connect to the scheduler at ``address`` (``tls://HOST:PORT``, ``tcp://HOST:PORT``, ``HOST:PORT``, or a
    scheduler file that ``dask scheduler --scheduler-file`` wrote) with ``security`` (a ``distributed.Security``:
    clusterauth.client_security; None: no TLS, ``--insecure-cluster``), once it has a worker. ``advertise`` is where the
    workers reach this machine; by default the address this machine reaches the scheduler from. ``ClusterUsage``
    for bad input, ``ClusterError`` if the scheduler does not answer, refuses the connection (TLS), or has no worker
    within ``WORKERS_TIMEOUT_S``."""
    try:
        import distributed  # noqa: PLC0415  (an extra: only --cluster needs it)
    except ImportError:
        raise ClusterUsage(f"--cluster needs Dask distributed, which is not installed: {INSTALL}") from None
    scheme, host, port = scheduler_address(address)
    try:  # a plain connection first: a scheduler nobody runs is told at once, without Dask's retries
        with socket.create_connection((host, port), timeout=timeout_s) as probe:
            here = probe.getsockname()[0]
            if security is not None:
                _handshake(probe, security, address)
    except OSError as exc:
        raise ClusterError(f"--cluster {address}: cannot reach the Dask scheduler at {host}:{port}: "
                           f"{exc.strerror or exc}") from None
    try:
        client = distributed.Client(f"{scheme}://{_join(host, port)}", timeout=timeout_s, set_as_default=False,
                                    security=security)
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"--cluster {address}: the Dask scheduler did not answer or refused this connection: "
                           f"{' '.join(str(exc).split())}") from None
    try:
        client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S)
    except (TimeoutError, OSError):
        client.close()
        raise ClusterError(f"--cluster {address}: the scheduler has had no worker for {WORKERS_TIMEOUT_S:g} s "
                           "(docs/cluster.md, \"Starting a cluster\")") from None
    return Cluster(client, address, advertise or here)


def _handshake(connection: socket.socket, security, address: str) -> None:
    """``ClusterError`` unless a TLS handshake with ``security``'s certificates succeeds on ``connection``: a
    scheduler without TLS, or with certificates of another CA, is told in one line (Dask would fail with an error of
    its internals, or wait)."""
    context = security.get_connection_args("client")["ssl_context"]
    try:
        context.wrap_socket(connection).close()
    except (ssl.SSLError, OSError) as exc:
        why = getattr(exc, "reason", None) or exc
        raise ClusterError(f"--cluster {address}: TLS with the scheduler failed ({why}): is it a scheduler started "
                           "with the certificates of --cluster-auth's DIR/scheduler/ (docs/cluster.md)?") from None


def scheduler_address(text: str) -> tuple[str, str, int]:
    """``--cluster``'s value as (scheme, host, port): an address, or a scheduler file's; ``ClusterUsage`` names what
    is wrong."""
    if "://" not in text and not _host_port(text) and Path(text).is_file():
        text = _from_scheduler_file(Path(text))
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    if scheme not in SCHEMES:
        raise ClusterUsage(f"--cluster {text}: a Dask scheduler is reached by {' or '.join(s + '://' for s in SCHEMES)}"
                           f"HOST:PORT, not {scheme}://")
    found = _host_port(rest)
    if found is None:
        raise ClusterUsage(f"--cluster {text}: expected a scheduler's address, tls://HOST:PORT (e.g. "
                           "tls://10.0.0.5:8786), or the file of dask scheduler --scheduler-file")
    return scheme, *found


def _host_port(text: str) -> tuple[str, int] | None:
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536 or any(c in host for c in "/ @"):
        return None
    return host, int(port)


def _join(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _from_scheduler_file(path: Path) -> str:
    try:
        with path.open("rb") as f:
            data = json.loads(f.read(MAX_SCHEDULER_FILE + 1)[:MAX_SCHEDULER_FILE])
        return str(data["address"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ClusterUsage(f"--cluster {path}: not a Dask scheduler file (JSON with its \"address\"): {exc}") from None


def endpoint(scheme: str, host: str, port: int) -> str:
    """A Zenoh endpoint: ``tcp/HOST:PORT``, an IPv6 host in brackets."""
    return f"{scheme}/{_join(host, port)}"


def read_token(path: str) -> str | None:
    """On a worker: the text of the probe file ``check_sees`` made, or None if it cannot read it."""
    try:
        return Path(path).read_text()
    except OSError:
        return None


def reaches(host: str, port: int) -> str | None:
    """On a worker: None if it can open a TCP connection to ``host`` at ``port``, else why not."""
    try:
        with socket.create_connection((host, port), timeout=REACH_TIMEOUT_S):
            return None
    except OSError as exc:
        return exc.strerror or str(exc)


def deal(names: list[str], workers: list[str]) -> dict[str, list[str]]:
    """``names`` dealt to ``workers`` in turn, so that no worker has more than one more than another; a worker
    dealt nothing is left out."""
    shares: dict[str, list[str]] = {}
    for i, name in enumerate(names):
        shares.setdefault(workers[i % len(workers)], []).append(name)
    return shares


# --- the lifeline ---------------------------------------------------------------------------------------------------

class Lifeline:
    """The launcher's end of a lifeline: a ``distributed.Variable`` named ``name`` beaten every ``BEAT_S`` from
    a thread of its own until ``cut``."""

    def __init__(self, client, name: str):
        from distributed import Variable  # noqa: PLC0415

        self.name = name
        self.variable = Variable(name, client=client)
        self.variable.set(0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"lifeline-{name}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        beats = 0
        while not self._stop.wait(BEAT_S):
            beats += 1
            try:
                self.variable.set(beats)
            except Exception:  # noqa: BLE001  (the scheduler is gone: the tasks stop when the beats do)
                return

    def cut(self) -> None:
        """Tell every task that watches the lifeline to stop its processes (once; again is a no-op)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join()
        try:
            self.variable.set(CUT)
        except Exception:  # noqa: BLE001  (the scheduler is gone: the tasks stop when they miss the beats)
            pass

    def remove(self) -> None:
        """Cut it and take it off the scheduler, once its tasks have ended (one still running stops when it
        misses the beats)."""
        self.cut()
        try:
            self.variable.delete()
        except Exception:  # noqa: BLE001  (the scheduler is gone, and the variable with it)
            pass


class Tether:
    """A task's end of a lifeline: ``cut()`` says whether to stop, reading the lifeline by ``read`` (which may fail:
    the scheduler out of reach for a moment is the same as no new beat)."""

    def __init__(self, read: Callable[[], object], clock: Callable[[], float] = time.monotonic,
                 lost_after_s: float = LOST_AFTER_S):
        self.read, self.clock, self.lost_after_s = read, clock, lost_after_s
        self.last: object = None
        self.since = clock()

    def cut(self) -> bool:
        try:
            value = self.read()
        except Exception:  # noqa: BLE001  (Dask's TimeoutError, a lost connection: no news)
            value = self.last
        now = self.clock()
        if value == CUT:
            return True
        if value != self.last:
            self.last, self.since = value, now
            return False
        return now - self.since > self.lost_after_s


def _tether(name: str) -> Tether:
    """On a worker: the tether of the lifeline ``name``."""
    from distributed import Variable  # noqa: PLC0415

    variable = Variable(name)
    return Tether(lambda: variable.get(timeout=TASK_POLL_S))


# --- a command on a worker (dmosim sweep --cluster) -----------------------------------------------------------------

def run_command(args: list[str], cwd: str, lifeline: str) -> tuple[int, str, str]:
    """On a worker: ``dmosim ARGS`` (this worker's dmosim) in directory ``cwd`` (the launcher's, if this worker has
    it), to its end or until the lifeline is cut; its exit code, stdout and stderr (``Command``: written to files,
    read at its end). Stopped, it gets SIGTERM (a ``dmosim run`` stops its roles), and after ``COMMAND_STOP_S`` SIGKILL
    with all it started (``stop_processes``)."""
    tether = _tether(lifeline)
    if tether.cut():  # stopped while this task waited for a thread
        return 1, "", CANCELLED
    command = Command(dmosim_command(*args), cwd=cwd if os.path.isdir(cwd) else None)
    try:
        while True:
            try:
                code = command.wait(TASK_POLL_S)
                break
            except subprocess.TimeoutExpired:
                if tether.cut():
                    stop_processes([command.process], COMMAND_STOP_S)
                    code = command.poll()
                    break
        return code, *command.output()
    finally:  # the task itself failed: nothing of the command may be left
        stop_processes([command.process], 0.0)


class Commands:
    """``dmosim`` commands run as tasks on the cluster's workers, each watched by ``poll`` as a process is, all
    stopped by ``stop`` (Ctrl-C: those not started are cancelled, those under way stopped by the lifeline)."""

    def __init__(self, cluster: Cluster):
        self.cluster = cluster
        self.lifeline = Lifeline(cluster.client, f"dmosim-sweep-{secrets.token_hex(8)}")
        self.futures: list = []

    def start(self, args: list[str], name: str) -> Callable[[], tuple[int, str, str] | None]:
        """Submit ``dmosim ARGS`` (``name`` names the task); a function that returns None while it runs, then its
        exit code, stdout and stderr (exit 1 and why if the cluster lost it)."""
        future = self.cluster.client.submit(run_command, args, os.getcwd(), self.lifeline.name, pure=False,
                                            key=f"{name}-{secrets.token_hex(4)}", retries=0)
        self.futures.append(future)

        def poll() -> tuple[int, str, str] | None:
            if not future.done():
                return None
            if future.cancelled():
                return 1, "", CANCELLED
            try:
                return future.result()
            except Exception as exc:  # noqa: BLE001  (its worker died, or the task failed there)
                return 1, "", f"the cluster lost this run: {type(exc).__name__}: {exc}"

        return poll

    def stop(self) -> None:
        """Cancel what has not started, stop what runs, and wait for it to be stopped."""
        self.lifeline.cut()  # a task that starts from now on returns at once
        waiting = [f for f in self.futures if not f.done()]
        self.cluster.client.cancel([f for f in waiting if self._queued(f)])
        _await(waiting, COMMAND_STOP_S + TASK_POLL_S + 30)
        self.lifeline.remove()

    def _queued(self, future) -> bool:
        """Whether the task of ``future`` is still with the scheduler, given to no worker: cancelled, it is gone at
        once (one given to a worker returns at once when it starts after the cut)."""
        processing = self.cluster.client.processing()  # worker -> keys under way
        return not any(future.key in keys for keys in processing.values())


def _await(futures: list, timeout_s: float) -> None:
    """Wait until every one of ``futures`` is done (or cancelled), at most ``timeout_s`` in all, whatever each ends
    with (distributed.wait would need a default client)."""
    deadline = time.monotonic() + timeout_s
    for future in futures:
        if future.cancelled():
            continue
        try:
            future.result(timeout=max(0.0, deadline - time.monotonic()))
        except Exception:  # noqa: BLE001  (its failure is the caller's to read; a timeout: the next one)
            pass


# --- agents on the workers (dmosim run --cluster) -------------------------------------------------------------------

def host_agents(agents: list[tuple[str, list[str], str]], bundles: dict[str, dict[str, str]],
                modules: tuple[str, ...] | None, host_log: str | None, cwd: str, lifeline: str,
                exits: str) -> dict[str, int | None]:
    """On a worker: one run's share of agents, ``(name, dmosim ARGS, log)`` each, started as processes of their
    own, or with ``modules`` forked from one host that has imported them (its log ``host_log``), in directory ``cwd``
    (the launcher's, if this worker has it), each logging in with its bundle of ``bundles`` (by name, its files'
    text), written for the time they run to a private directory of this worker, their ``--auth-dir``; each exit put
    on the ``distributed.Queue`` ``exits`` as it comes; every one stopped when the lifeline is cut. Returns each
    agent's exit code (None: it never started). It leaves the worker's thread pool: agents must start now, not when a
    thread is free."""
    from distributed import Queue, secede  # noqa: PLC0415

    secede()
    tether, reported = _tether(lifeline), Queue(exits)
    codes: dict[str, int | None] = {}
    if tether.cut():  # the run was over before this task started
        return {name: None for name, _, _ in agents}
    directory = Path(cwd) if os.path.isdir(cwd) else None
    # the credentials go once the agents are stopped (the context managers end in reverse order)
    with tempfile.TemporaryDirectory(prefix="dmosim-agents-") as auth, Roles() as roles:
        for name, files in bundles.items():
            write_bundle(auth, name, files)
        host = roles.fork_host(modules, Path(host_log) if host_log else None) if modules else None
        for name, args, log in agents:
            roles.start(name, dmosim_command(*args, "--auth-dir", auth), log=Path(log), env=role_env(), cwd=directory,
                        host=host)
        while len(codes) < len(agents):
            try:
                name, code = roles.exits.get(timeout=TASK_POLL_S)
            except queue.Empty:
                if tether.cut():
                    break
                continue
            codes[name] = code
            reported.put([name, code])
        roles.stop_all(ROLE_STOP_S)  # those still running once the lifeline is cut
    return {name: codes.get(name, roles.roles[name].process.returncode if name in roles.roles else None)
            for name, _, _ in agents}


class RemoteAgents:
    """The launcher's side of a run's agents on the cluster: ``start`` deals them to the workers, one task a
    worker; each agent's exit comes on ``exits`` as ``(name, code)``, as ``Roles`` reports its own, once (-9 if it
    was lost with its worker or task); as a context manager it stops every one of them, whatever happens."""

    def __init__(self, cluster: Cluster, run_id: str, exits: queue.Queue):
        from distributed import Queue  # noqa: PLC0415

        self.cluster, self.exits = cluster, exits
        self.lifeline = Lifeline(cluster.client, f"dmosim-run-{run_id}-{secrets.token_hex(4)}")
        self.queue = Queue(f"{self.lifeline.name}-exits", client=cluster.client)
        self.futures: dict[object, list[str]] = {}  # future -> the agents of its task
        self.placed: dict[str, list[str]] = {}  # worker -> its agents
        self.reported: set[str] = set()
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._watcher: threading.Thread | None = None

    @property
    def names(self) -> list[str]:
        return [name for share in self.placed.values() for name in share]

    def start(self, agents: list[tuple[str, list[str], Path]], bundles: dict[str, dict[str, str]],
              modules: tuple[str, ...] | None, host_log: Callable[[int], Path]) -> dict[str, list[str]]:
        """Start ``(name, dmosim ARGS, log)`` dealt to the workers (``deal``), each with its bundle of ``bundles``
        (``messages.transport.credentials.read_bundle``), with ``modules`` forked from one host a worker (its log
        ``host_log(i)`` for the i-th worker) or as processes; returns worker -> its agents. A worker's task carries
        the bundles of its own agents only."""
        of = {name: (name, args, str(log)) for name, args, log in agents}
        self.placed = deal(list(of), self.cluster.workers())
        for i, (worker, names) in enumerate(self.placed.items()):
            future = self.cluster.client.submit(
                host_agents, [of[n] for n in names], {n: bundles[n] for n in names}, modules,
                str(host_log(i)) if modules else None, os.getcwd(),
                self.lifeline.name, self.queue.name, workers=[worker], allow_other_workers=False, pure=False,
                retries=0, key=f"dmosim-agents-{i}-{self.lifeline.name}")
            self.futures[future] = names
        self._watcher = threading.Thread(target=self._watch, name="remote-agents", daemon=True)
        self._watcher.start()
        return self.placed

    def _report(self, name: str, code: int) -> None:
        with self._lock:
            if name in self.reported:
                return
            self.reported.add(name)
        self.exits.put((name, code))

    def _watch(self) -> None:
        """Pass each exit the tasks report on, and those of agents whose task ended without reporting them or whose
        worker left the cluster (its task would wait for it forever: it may run there only)."""
        worker_of = {name: worker for worker, names in self.placed.items() for name in names}
        while not self._done.is_set() and len(self.reported) < len(self.names):
            try:
                name, code = self.queue.get(timeout=TASK_POLL_S)
                self._report(name, code)
                continue
            except TimeoutError:  # nothing new
                pass
            except Exception:  # noqa: BLE001  (the scheduler out of reach: the tasks' futures will say so)
                self._done.wait(TASK_POLL_S)
            for future, names in list(self.futures.items()):
                if future.done():
                    codes = self._codes(future)
                    for name in names:
                        self._report(name, codes.get(name) if codes.get(name) is not None else -signal.SIGKILL)
            try:
                present = self.cluster.client.scheduler_info()["workers"]
            except Exception:  # noqa: BLE001  (the scheduler out of reach: the futures will say so)
                continue
            for name in [n for n, worker in worker_of.items() if worker not in present]:
                self._report(name, -signal.SIGKILL)

    @staticmethod
    def _codes(future) -> dict:
        try:
            return future.result()
        except Exception:  # noqa: BLE001  (its worker died or the task failed: its agents are lost)
            return {}

    def stop(self) -> dict[str, int | None]:
        """Stop every agent still running (the lifeline cut) and wait for the tasks to end; each agent's exit code."""
        self.lifeline.cut()
        _await(list(self.futures), ROLE_STOP_S + 2 * TASK_POLL_S + 30)
        self._done.set()
        if self._watcher is not None:
            self._watcher.join()
        self.lifeline.remove()
        try:
            self.queue.close()
        except Exception:  # noqa: BLE001  (the scheduler is gone, and the queue with it)
            pass
        codes: dict[str, int | None] = {}
        for future, names in self.futures.items():
            codes.update(self._codes(future) if future.done() else {})
            for name in names:  # those the watcher had not passed on yet
                self._report(name, codes[name] if codes.get(name) is not None else -signal.SIGKILL)
        return codes

    def __enter__(self) -> RemoteAgents:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
