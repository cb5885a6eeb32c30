"""Commands that start processes of their own (``dmosim run`` its roles, ``sweep`` its runs, ``bench`` its run) never
wait for ever on them: a run's output, however large, is read once it has ended, and SIGTERM ends the command within
10 s and exits 130 whatever its processes are doing (blocked writing, ignoring SIGTERM, with processes of their own
below them), leaving none behind; nor does a reader that stops reading the command's own output hold it.

Every test runs the real command in a process of its own, so all are in the slow tier. Most put a stand-in in place
of each ``dmosim run`` it starts (``BIG_RUN``, ``STUCK_RUN``: real processes, put in through the command line its
module builds, ``dmosim_command``), so that no market day is needed; the others run real market days and stop them
once their DMO runs."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from dmosim.bench.fleet import role_of
from dmosim.launch.processes import descendants, proc_stat
from dmosim.results.report import result_text
from tests.dmosim.synthetic import typed

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
STOPPED_WITHIN_S = 10.0  # README: Ctrl-C or SIGTERM stops a run, sweep or bench with everything it started
TINY = 'name = "tiny"\nmarket_day = "2026-07-01"\n[agents]\ncount = 1\n'

pytestmark = pytest.mark.slow
# A real day of one agent whose hours each wait 5 s for its meter report: two minutes, stopped in its first.
SLOW = ('faults = ["delay:agent/mg1/meter:5"]\n' + TINY + "[market]\nsubperiods = 1\n[schedule]\nscenarios = 1\n"
        "gap = 0.05\ntime_limit = 60.0\n[deadlines]\nbid = 120.0\nschedule = 120.0\nhour = 60.0\n")
BIG = 2 << 20  # bytes of BIG_RUN's --json: more than 1 MiB, and far more than a pipe holds (64 KiB)

# A `dmosim run --json` that writes 256 KiB on stderr, then a result of BIG bytes on stdout (a whole result, whose
# `logs` is BIG bytes long).
BIG_RUN = f"""
import json, sys
sys.stderr.write("e" * (256 << 10) + "\\n")
result = json.loads({result_text(typed({"settlement": {"mg1": {"total": 12.5}}}))!r})
json.dump({{**result, "logs": "x" * {BIG}}}, sys.stdout)
"""

# A `dmosim run` that ignores SIGTERM, has started a process in a group of its own (as a run's roles are) that
# ignores it too, writes both pids to the file $PIDS, and then blocks writing to a pipe nobody reads.
STUCK_RUN = """
import os, signal, subprocess, sys
signal.signal(signal.SIGTERM, signal.SIG_IGN)
below = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                          "time.sleep(600)"], process_group=0)
with open(os.environ["PIDS"] + ".part", "w") as f:
    f.write(f"{os.getpid()} {below.pid}")
os.rename(os.environ["PIDS"] + ".part", os.environ["PIDS"])
_, w = os.pipe()
os.write(w, b"x" * (1 << 20))
"""

# `dmosim ARGS...` with the stand-in CHILD for every `dmosim run` that MODULE starts: driver.py MODULE CHILD ARGS...
DRIVER = """
import importlib, sys
module, child = importlib.import_module(sys.argv[1]), sys.argv[2]
module.dmosim_command = lambda *args: [sys.executable, child, *args]
from dmosim.cli.main import main
sys.exit(main(sys.argv[3:]))
"""


def _standing_in(tmp_path: Path, module: str, child: str, *args: str) -> list[str]:
    (tmp_path / "driver.py").write_text(DRIVER)
    (tmp_path / "child.py").write_text(child)
    return [sys.executable, str(tmp_path / "driver.py"), module, str(tmp_path / "child.py"), *args]


def _sweep(tmp_path: Path, child: str, *flags: str) -> list[str]:
    (tmp_path / "tiny.toml").write_text(TINY)
    return _standing_in(tmp_path, "dmosim.cli.sweep", child, "sweep", str(tmp_path / "tiny.toml"), "--set",
                        "market.penalty=0,400", "--out", str(tmp_path / "sweep"), *flags)


def test_a_sweep_reads_the_output_of_each_run_however_large(tmp_path):
    done = subprocess.run(_sweep(tmp_path, BIG_RUN, "--json", "--quiet"), capture_output=True, text=True,
                          timeout=120, cwd=tmp_path, env=ENV)
    assert done.returncode == 0, done.stderr[-2000:]
    table = pd.read_csv(json.loads(done.stdout)["table"])
    assert list(table["status"]) == ["ok", "ok"] and list(table["total"]) == [12.5, 12.5]


def test_a_terminated_sweep_kills_a_run_that_is_blocked_and_ignores_sigterm(tmp_path):
    pids = tmp_path / "pids"
    argv = _sweep(tmp_path, STUCK_RUN, "--parallel", "1", "--quiet")
    _terminated(argv, {**ENV, "PIDS": str(pids)}, tmp_path, lambda command: _pids_of(pids))


def test_a_terminated_bench_kills_a_run_that_is_blocked_and_ignores_sigterm_and_removes_its_directory(tmp_path):
    pids, scratch = tmp_path / "pids", tmp_path / "tmp"  # scratch: where the bench's run directory goes (TMPDIR)
    scratch.mkdir()
    argv = _standing_in(tmp_path, "dmosim.bench.day", STUCK_RUN, "bench", "day", "--agents", "1")
    _terminated(argv, {**ENV, "PIDS": str(pids), "TMPDIR": str(scratch)}, tmp_path, lambda command: _pids_of(pids))
    assert list(scratch.iterdir()) == []


def test_a_terminated_sweep_whose_reader_has_stopped_reading_exits(tmp_path):
    """Its runs over, the sweep writes its result to a pipe that is full: SIGTERM ends it all the same."""
    read, write = os.pipe()
    fcntl.fcntl(write, fcntl.F_SETFL, os.O_NONBLOCK)
    with pytest.raises(BlockingIOError):
        while True:
            os.write(write, b"x" * 4096)
    fcntl.fcntl(write, fcntl.F_SETFL, 0)
    try:
        sweep = subprocess.Popen(_sweep(tmp_path, BIG_RUN, "--json", "--quiet"), stdout=write, stderr=subprocess.PIPE,
                                 cwd=tmp_path, env=ENV)
    finally:
        os.close(write)
    try:
        _await(lambda: "pipe_write" in _wchan(sweep.pid), sweep, 120, "the sweep writing its result")
        took, code, err = _terminate(sweep)
        assert (code, err.strip().endswith("interrupted")) == (130, True), err[-2000:]
        assert took < STOPPED_WITHIN_S
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.communicate()
        os.close(read)


def test_a_terminated_run_stops_its_roles(tmp_path):
    (tmp_path / "slow.toml").write_text(SLOW)
    _terminated([sys.executable, "-m", "dmosim", "run", str(tmp_path / "slow.toml"), "--out", str(tmp_path / "run")],
                ENV, ROOT, _once_a_dmo_runs)


def test_a_terminated_sweep_stops_its_runs_and_their_roles(tmp_path):
    (tmp_path / "slow.toml").write_text(SLOW)
    _terminated([sys.executable, "-m", "dmosim", "sweep", str(tmp_path / "slow.toml"), "--set", "market.penalty=400",
                 "--out", str(tmp_path / "sweep"), "--quiet"], ENV, ROOT, _once_a_dmo_runs)


def test_a_terminated_bench_stops_its_run_and_its_roles_and_leaves_no_scratch_directory(tmp_path):
    scratch = tmp_path / "tmp"  # where the bench's run directory goes (TMPDIR)
    scratch.mkdir()
    _terminated([sys.executable, "-m", "dmosim", "bench", "day", "--agents", "3", "--scenarios", "1"],
                {**ENV, "TMPDIR": str(scratch)}, ROOT, _once_a_dmo_runs)
    assert list(scratch.iterdir()) == []


def _terminated(argv: list[str], env: dict, cwd: Path, started) -> None:
    """Start ``argv``; once ``started(command)`` names the pids of what it started, SIGTERM it: it exits 130 within
    ``STOPPED_WITHIN_S``, and every one of those processes is gone."""
    command = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env,
                               start_new_session=True)
    tree: dict[int, str | None] = {}
    try:
        _await(lambda: bool(started(command)), command, 120, "what it starts")
        tree = {pid: _started_at(pid) for pid in started(command)}
        took, code, err = _terminate(command)
        assert (code, err.strip().endswith("interrupted")) == (130, True), err[-2000:]
        assert took < STOPPED_WITHIN_S
        # Killed, a process is gone at once; one orphaned by it is reaped by init soon after.
        _await(lambda: not any(_alive(pid, at) for pid, at in tree.items()), None, 10, "its processes' end")
    finally:
        for pid, at in tree.items():
            if _alive(pid, at):
                os.kill(pid, signal.SIGKILL)
        if command.poll() is None:
            command.kill()
        command.communicate()


def _pids_of(path: Path) -> list[int]:
    """The pids a STUCK_RUN wrote, once it has."""
    return [int(pid) for pid in path.read_text().split()] if path.exists() else []


def _once_a_dmo_runs(command: subprocess.Popen) -> list[int]:
    """Every process below ``command`` once one of them is a DMO, else none."""
    tree = descendants(command.pid)
    if not any(role_of(pid, parent, command.pid) == "dmo" for pid, parent in tree):
        return []
    return [pid for pid, _ in tree if pid != command.pid]


def _terminate(command: subprocess.Popen) -> tuple[float, int, str]:
    """SIGTERM ``command``: how long it took to exit (at most 60 s are waited), its exit code and its stderr."""
    sent = time.monotonic()
    command.terminate()
    _, err = command.communicate(timeout=60)
    err = err.decode(errors="replace") if isinstance(err, bytes) else err
    return time.monotonic() - sent, command.returncode, err


def _await(condition, command: subprocess.Popen | None, timeout_s: float, what: str) -> None:
    """Return once ``condition()`` holds; fail if ``command`` exits first or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if command is not None and command.poll() is not None:
            pytest.fail(f"the command exited {command.returncode} before {what}")
        if time.monotonic() > deadline:
            pytest.fail(f"no sign of {what} within {timeout_s:g} s")
        time.sleep(0.05)  # paces the looks at a file or /proc: there is nothing else to wait on


def _wchan(pid: int) -> str:
    """Where in the kernel the process waits (``anon_pipe_write``: for room in a full pipe)."""
    try:
        return Path(f"/proc/{pid}/wchan").read_text()
    except OSError:
        return ""


def _started_at(pid: int) -> str | None:
    """When the process started (clock ticks since boot): with its pid, which process it is, also once its pid may
    have been given to another."""
    return (proc_stat(pid) or [None] * 20)[19]


def _alive(pid: int, started_at: str | None) -> bool:
    """Whether the process that had ``pid`` and started at ``started_at`` runs (a zombie, ended but not yet reaped,
    does not)."""
    fields = proc_stat(pid)
    return bool(fields) and fields[0] != "Z" and fields[19] == started_at
