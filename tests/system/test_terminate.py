"""SIGTERM to a command that started runs of its own (``dmosim sweep``, ``dmosim bench``): it stops them, and
each run its roles, as Ctrl-C does, and exits 130; nothing it started is left running."""

from __future__ import annotations

import os
import signal
import subprocess
import time

from test_market_day import ENV, ROOT, dmosim
from test_sweep import EXPERIMENT

from dmosim.bench.fleet import role_of
from dmosim.launch.processes import descendants, proc_stat

# Each hour waits 5 s for mg1's meter report: the day would last two minutes; the command is stopped in its first.
SLOW = 'faults = ["delay:agent/mg1/meter:5"]\n' + EXPERIMENT


def test_a_sweep_terminated_stops_its_runs_and_their_roles(tmp_path):
    (tmp_path / "slow.toml").write_text(SLOW)
    _terminated_once_a_dmo_runs(dmosim("sweep", str(tmp_path / "slow.toml"), "--set", "market.penalty=400", "--out",
                                       str(tmp_path / "sweep"), "--quiet"))


def test_a_bench_terminated_stops_its_run_and_its_roles_and_leaves_no_scratch_directory(tmp_path):
    scratch = tmp_path / "tmp"  # where the bench's run directory goes (TMPDIR)
    scratch.mkdir()
    _terminated_once_a_dmo_runs(dmosim("bench", "day", "--agents", "3", "--scenarios", "1"),
                                {**ENV, "TMPDIR": str(scratch)})
    assert list(scratch.iterdir()) == []


def _terminated_once_a_dmo_runs(argv: list[str], env: dict = ENV) -> None:
    command = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
                               start_new_session=True)
    tree = []
    try:
        deadline = time.monotonic() + 120
        while not any(role_of(pid, parent, command.pid) == "dmo" for pid, parent in tree):
            assert command.poll() is None and time.monotonic() < deadline, "the command's run never started its DMO"
            time.sleep(0.1)  # paces the look at /proc: nothing to wait on but the processes appearing
            tree = descendants(command.pid)
        started = {pid: _started_at(pid) for pid, _ in tree if pid != command.pid}
        command.terminate()
        _, err = command.communicate(timeout=120)
        assert command.returncode == 130 and err.strip().endswith("interrupted"), err[-2000:]
        left = {pid: _command_line(pid) for pid, at in started.items() if _alive(pid, at)}
        assert left == {}  # the run and every role it started
    finally:
        for pid, _ in tree:
            if _alive(pid, _started_at(pid)):
                os.kill(pid, signal.SIGKILL)
        command.communicate()


def _started_at(pid: int) -> str | None:
    """When the process started (clock ticks since boot): with its pid, which process it is, also once its pid
    may have been given to another (pids wrap at 32,768 here)."""
    return (proc_stat(pid) or [None] * 20)[19]


def _alive(pid: int, started_at: str | None) -> bool:
    """Whether the process that had ``pid`` and started at ``started_at`` runs (a zombie, ended but not yet reaped,
    does not)."""
    fields = proc_stat(pid)
    return bool(fields) and fields[0] != "Z" and fields[19] == started_at


def _command_line(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline") as f:
            return f.read().replace("\0", " ")
    except OSError:
        return "(gone)"
