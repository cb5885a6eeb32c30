"""Start, watch and always stop the OS processes of one run: every role in its own process group, started as a
process of its own or forked from a pre-loaded host (host.py).

A role leads a process group (a signal to it reaches whatever it started; the terminal's Ctrl-C does not) in the
session of the command that started it, never a session of its own: Linux shares the cores among sessions first
(autogroup, on by default), so a role in a session of its own got as much of them as every agent together, and a
forked host's hundreds of agents, one session between them, were starved for up to a minute while the DMO, the
routers and the recorder each had a share as large (docs/benchmarks.md, "fleet"). dmosim's other launchers (the
agents' host, ``dmosim bench``, a cluster's task) start their processes so too (``process_group=0``).

Every one of them is stopped the same way (``stop_processes``): SIGTERM to its group, and after a grace SIGKILL to
it and to everything below it, whatever each is doing (solving, blocked, ignoring SIGTERM). A command whose output
its starter reads (``Command``: a ``dmosim run --json`` under a sweep or a benchmark) writes it to files, never to a
pipe that nobody reads while it runs."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager, nullcontext, suppress
from dataclasses import dataclass
from pathlib import Path

from .host import ForkHost, Forked

# The directory that holds the dmo package: a role started with role_env() imports this very dmosim.
SOURCE_ROOT = Path(__file__).resolve().parents[2]


CLI_ENTRY = "dmosim.cli.main:main"  # what ``dmosim ARGS`` calls with ARGS: a group's thread calls it (host.py)
ROLE_STOP_S = 5.0  # how long a stopped role has to leave (the recorder: to finish its file) before SIGKILL
# How long a stopped ``dmosim run`` (a sweep's, a benchmark's) has to stop its roles (``ROLE_STOP_S``) and leave before
# SIGKILL reaches it and all it started: a command stopped by Ctrl-C or SIGTERM ends within 10 s, whatever its runs do.
COMMAND_STOP_S = 6.0


def dmosim_command(*args: str) -> list[str]:
    """The command line of ``dmosim ARGS`` in a new process of this interpreter."""
    return [sys.executable, "-m", "dmosim", *args]


def role_env() -> dict:
    """This environment, with the directory of this dmosim first on PYTHONPATH (for a checkout not installed)."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(SOURCE_ROOT), os.environ.get("PYTHONPATH")]))}


@contextmanager
def interrupts_held():
    """Hold Ctrl-C and SIGTERM until the block ends, then deliver the first that came as if it came then.

    Around starting a process and recording it: an interrupt between the two (Popen reads its pipe to the child,
    a watcher thread starts) would raise KeyboardInterrupt before the caller knows of the process, and leave it
    running in a process group of its own, never stopped. Only in the main thread, where Python runs signal handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    previous = {sig: signal.signal(sig, lambda sig, _: came.append(sig)) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        if came:
            signal.raise_signal(came[0])


def free_port() -> int:
    """A TCP port on loopback that nobody listens on now (the OS picks it; no fixed ports)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, timeout_s: float, alive) -> None:
    """Return once something accepts connections on the port; fail if ``alive()`` turns false or time runs out."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if not alive():
            raise RuntimeError("the DMO exited before it listened")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)  # a connect refused returns at once; this only paces the retries
    raise RuntimeError(f"nothing listened on port {port} within {timeout_s:g} s")


def memory_mib(pid: int) -> dict[str, float] | None:
    """A live process's resident memory now and its peak so far (VmRSS, VmHWM of /proc/PID/status), and its
    proportional share now (Pss of /proc/PID/smaps_rollup: each page shared with other processes counted as its
    share, so that the roles' PSS add up to what the run holds), MiB; None where there is no /proc or the process
    is gone (``pss_mib`` None where the kernel has no smaps_rollup). Its own children (Benders workers) are not
    counted."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if line.startswith(("VmRSS", "VmHWM")))
    if len(fields) < 2:
        return None
    return {"rss_mib": round(int(fields["VmRSS"].split()[0]) / 1024, 1),
            "peak_mib": round(int(fields["VmHWM"].split()[0]) / 1024, 1), "pss_mib": _pss_mib(pid)}


def _pss_mib(pid: int) -> float | None:
    try:
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    kib = next((line.split()[1] for line in rollup.splitlines() if line.startswith("Pss:")), None)
    return None if kib is None else round(int(kib) / 1024, 1)


@dataclass
class Role:
    name: str
    process: subprocess.Popen | Forked
    log: Path | None
    killed_on_purpose: bool = False
    argv: tuple[str, ...] = ()
    env: dict | None = None
    cwd: Path | None = None
    restarts: int = 0
    host: ForkHost | None = None  # the host it is forked from (restarted from it too); None: a process of its own
    shared_by: int = 1  # how many roles its process runs (``Roles.start_group``)


class Roles:
    """The processes of one run. As a context manager it stops every process it started, whatever happens.

    ``exits`` is a queue of (name, returncode) filled by one waiter thread per process, so the caller can block
    on the next exit instead of polling. A role started with ``host`` (``fork_host``) is forked from that host
    instead of started as a process: the same command, watched, restarted, killed and stopped the same way; the
    hosts are stopped after every role.
    """

    def __init__(self):
        self.roles: dict[str, Role] = {}
        self.exits: queue.Queue = queue.Queue()
        self.hosts: list[ForkHost] = []
        self._replaced: set[int] = set()  # pids of processes restarted on purpose: their exits are not reported

    def fork_host(self, modules: tuple[str, ...], log: Path | None = None) -> ForkHost:
        """Start a host that imports ``modules`` (host.py), for roles to be forked from (``start(..., host=)``);
        its own errors go to ``log``. It imports this very dmosim, as ``role_env`` makes sure."""
        with interrupts_held():
            host = ForkHost(modules, log, role_env())
            self.hosts.append(host)
        return host

    def start(self, name: str, argv: list[str], log: Path | None = None, env: dict | None = None,
              cwd: Path | None = None, host: ForkHost | None = None) -> Role:
        with self._held(host):
            role = Role(name, self._spawn(name, argv, log, env, cwd, "w", host), log, argv=tuple(argv), env=env,
                        cwd=cwd, host=host)
            self.roles[name] = role
        return role

    @staticmethod
    def _held(host: ForkHost | None):
        """``interrupts_held`` around a process started here; a child forked by ``host`` needs none (the host stops
        every child it has when it is stopped), and its start may wait seconds for the host to be ready."""
        return interrupts_held() if host is None else nullcontext()

    def start_group(self, host: ForkHost, roles: list[tuple[str, list[str], Path]]) -> list[Role]:
        """Start ``roles`` (name, ``dmosim_command(...)``, log) in one child of ``host``, each in a thread of its own
        calling the command line's entry point with its arguments (host.py). They are watched and stopped as roles
        are, but share one process: a signal to one reaches them all, so none is killed or restarted alone."""
        for _, argv, _ in roles:
            if list(argv[:3]) != dmosim_command():
                raise ValueError(f"a group runs dmosim commands, not {argv}")
        forked = host.start_group(CLI_ENTRY, [(name, list(argv[3:]), log) for name, argv, log in roles])
        started = []
        for (name, argv, log), process in zip(roles, forked):
            self._watch(name, process, None)
            role = self.roles[name] = Role(name, process, log, argv=tuple(argv), host=host, shared_by=len(roles))
            started.append(role)
        return started

    def _spawn(self, name: str, argv, log: Path | None, env: dict | None, cwd: Path | None,
               mode: str, host: ForkHost | None) -> subprocess.Popen | Forked:
        if host is not None:
            out, process = None, host.start(list(argv), log, mode, env, cwd)
        else:
            out = open(log, mode) if log else None  # noqa: SIM115  (closed when the process ends)
            process = subprocess.Popen(list(argv), stdin=subprocess.DEVNULL, stdout=out or subprocess.DEVNULL,
                                       stderr=out or None, process_group=0, env=env, cwd=cwd)
        self._watch(name, process, out)
        return process

    def _watch(self, name: str, process: subprocess.Popen | Forked, out) -> None:
        """Put (name, returncode) on ``exits`` when ``process`` ends (unless restarted on purpose); close ``out``."""

        def waiter():
            code = process.wait()
            if out:
                out.close()
            if process.pid not in self._replaced:
                self.exits.put((name, code))

        threading.Thread(target=waiter, name=f"wait-{name}", daemon=True).start()

    def restart(self, name: str) -> None:
        """SIGKILL one role and start it again with the same command line, its log continued (fault injection)."""
        role = self._alone(name)
        old = role.process
        self._replaced.add(old.pid)
        _signal_group(old, signal.SIGKILL)
        old.wait()
        role.restarts += 1
        with self._held(role.host):
            role.process = self._spawn(name, role.argv, role.log, role.env, role.cwd, "a", role.host)

    def kill(self, name: str) -> None:
        """SIGKILL one role (fault injection)."""
        role = self._alone(name)
        role.killed_on_purpose = True
        _signal_group(role.process, signal.SIGKILL)

    def _alone(self, name: str) -> Role:
        role = self.roles[name]
        if role.shared_by > 1:
            raise ValueError(f"{name} shares its process with {role.shared_by - 1} other role(s): it cannot be "
                             "killed or restarted alone")
        return role

    def stop_all(self, grace_s: float = ROLE_STOP_S) -> None:
        """Stop every role still running (``stop_processes``), then the hosts they were forked from."""
        stop_processes([r.process for r in self.roles.values()], grace_s)
        for host in self.hosts:
            host.stop(grace_s)

    def __enter__(self) -> Roles:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def _signal_group(process: subprocess.Popen | Forked, sig: int) -> None:
    try:
        os.killpg(process.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def stop_processes(processes: list, grace_s: float) -> None:
    """Stop each of ``processes`` (a ``subprocess.Popen`` or a ``Forked``, each leading its process group) still
    running: SIGTERM to its group, and to those still there ``grace_s`` later (one deadline for all), SIGKILL to
    them and to everything below them (``kill_tree``); return once every one has ended. A Ctrl-C or SIGTERM that
    comes meanwhile is held until then (``interrupts_held``): a second one must not cut the stopping short and leave
    processes behind, and this ends within the grace anyway."""
    with interrupts_held():
        running = [p for p in processes if p.poll() is None]
        for p in running:
            _signal_group(p, signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for p in running:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                kill_tree(p.pid)
                p.wait()


def kill_tree(root: int) -> None:
    """SIGKILL ``root``, every process below it and the process group of each (a role leads one: what it started
    without a group of its own is in it). All are stopped first (SIGSTOP, again for any that appeared meanwhile), so
    that none starts another while the rest are killed, and none escapes by being handed to init when its parent
    dies. The group of this process is never signalled."""
    stopped: set[int] = set()
    while fresh := {pid for pid, _ in descendants(root)} - stopped:
        for pid in fresh:
            _signal_pid(pid, signal.SIGSTOP)
        stopped |= fresh
    ours = os.getpgrp()
    groups = set()
    for pid in stopped:
        with suppress(ProcessLookupError, PermissionError):
            groups.add(os.getpgid(pid))
    for group in groups - {ours}:
        with suppress(ProcessLookupError, PermissionError):
            os.killpg(group, signal.SIGKILL)
    for pid in stopped:
        _signal_pid(pid, signal.SIGKILL)


def _signal_pid(pid: int, sig: int) -> None:
    with suppress(ProcessLookupError, PermissionError):
        os.kill(pid, sig)


def descendants(root: int) -> list[tuple[int, int]]:
    """(pid, parent pid) of ``root`` and every process below it, from /proc."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            parent = _parent(int(entry))
            if parent is not None:
                children.setdefault(parent, []).append(int(entry))
    out, todo = [], [(root, 0)]
    while todo:
        pid, parent = todo.pop()
        out.append((pid, parent))
        todo += [(child, pid) for child in children.get(pid, [])]
    return out


def proc_stat(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name (the state first, then the parent's pid; the start time
    is the 20th), or none if there is no such process."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rpartition(")")[2].split()
    except OSError:
        return []


def _parent(pid: int) -> int | None:
    fields = proc_stat(pid)
    return int(fields[1]) if len(fields) > 1 else None


class Command:
    """A command started as a process leading its own group, whose exit code, stdout and stderr its starter reads
    once it has ended (``output``). What it writes goes to two files of its own (unnamed, in the temporary
    directory), never to a pipe: a pipe holds 64 KiB, and a child that writes more than that to one nobody reads
    until it exits waits for ever (a two-day ``dmosim run --json`` writes 100 kB). Stopped with ``stop_processes``.
    Start it inside ``interrupts_held`` with whatever records it, so that a Ctrl-C cannot leave it unknown."""

    def __init__(self, argv: list[str], cwd: str | Path | None = None):
        self._out, self._err = tempfile.TemporaryFile(), tempfile.TemporaryFile()
        try:
            self.process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=self._out, stderr=self._err,
                                            process_group=0, env=role_env(), cwd=cwd)
        except BaseException:
            self._close()
            raise

    @property
    def pid(self) -> int:
        return self.process.pid

    def poll(self) -> int | None:
        return self.process.poll()

    def wait(self, timeout_s: float | None = None) -> int:
        """Its exit code once it has ended; ``subprocess.TimeoutExpired`` if it has not within ``timeout_s``."""
        return self.process.wait(timeout=timeout_s)

    def output(self) -> tuple[str, str]:
        """What it wrote to stdout and to stderr (once it has ended)."""
        said = []
        for file in (self._out, self._err):
            file.seek(0)
            said.append(file.read().decode("utf-8", errors="replace"))
        self._close()
        return said[0], said[1]

    def _close(self) -> None:
        self._out.close()
        self._err.close()
