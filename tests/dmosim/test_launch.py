"""What the launcher makes of its roles' exits (dmosim/launch/local.py): a role still there once the DMO is done; and
roles forked from a pre-loaded host (dmosim/launch/host.py), started, restarted, killed and stopped as processes are.

The launcher's decisions are checked on exits it is told of, in this process; whatever needs real processes (signals,
process groups, forks) is in the slow tier, and learns where a process has got from what it writes to a FIFO or from
its connections, never from its log."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest
from messages.recording import RecordingWriter

from dmosim.launch import local
from dmosim.launch.host import AgentStreams
from dmosim.launch.local import groups, wait_for_run
from dmosim.launch.mesh import router_names, spread
from dmosim.cli import main
from dmosim.launch.processes import Role, Roles, dmosim_command, interrupts_held, memory_mib

DONE = [sys.executable, "-c", "pass"]
STAYS = [sys.executable, "-c", "import time; time.sleep(120)"]


def told(*exits: tuple[str, int], restarted: tuple[str, ...] = (), staying: tuple[str, ...] = ()) -> Roles:
    """The roles of a run as the launcher knows them, no process started: each of ``exits`` (name, code) has ended
    in that order, and each of ``staying`` (``restarted``: restarted on purpose, as a restart fault does) has not."""
    roles = Roles()
    for name, code in exits:
        roles.roles[name] = Role(name, None, None)
        roles.exits.put((name, code))
    for name in staying:
        roles.roles[name] = Role(name, None, None, restarts=int(name in restarted))
    return roles


def wait(roles: Roles, routers: tuple[str, ...] = ()) -> tuple[list[str], list[str]]:
    said: list[str] = []
    return wait_for_run(roles, SimpleNamespace(say=said.append), leave_s=0.5, routers=routers), said


def test_an_agent_restarted_after_the_run_ended_is_stopped_not_failed():
    # the restarted agent waits for a DMO that has finished
    assert wait(told(("mg2", 0), ("dmo", 0), staying=("mg1",), restarted=("mg1",))) == (
        [], ["mg1 restarted after the run had ended: stopped"])


def test_an_agent_that_does_not_leave_after_the_run_has_failed():
    assert wait(told(("dmo", 0), staying=("mg1",))) == (["mg1"], [])


@pytest.mark.slow
def test_ctrl_c_while_a_role_starts_comes_once_it_is_recorded_and_stop_all_stops_it(monkeypatch):
    """A Ctrl-C between the fork and the bookkeeping (here: as its watcher thread starts) would leave the role
    running in a process group of its own, unknown to ``stop_all``."""
    watch = Roles._watch

    def interrupted(self, *args):
        os.kill(os.getpid(), signal.SIGINT)
        watch(self, *args)

    monkeypatch.setattr(Roles, "_watch", interrupted)
    with pytest.raises(KeyboardInterrupt), Roles() as roles:
        roles.start("mg1", STAYS)
    assert list(roles.roles) == ["mg1"] and roles.roles["mg1"].process.poll() is not None


def test_signals_held_in_a_block_arrive_once_at_its_end_and_the_handlers_are_restored():
    handler = signal.getsignal(signal.SIGINT)
    got = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            got.append("the block went on")
    assert got == ["the block went on"] and signal.getsignal(signal.SIGINT) is handler

    def elsewhere():
        with interrupts_held():  # another thread may not set handlers: there the block holds nothing, and works
            got.append("in a thread")

    outside = threading.Thread(target=elsewhere)
    outside.start()
    outside.join()
    assert got[-1] == "in a thread"


# A recorder that ignores SIGTERM: it has written what it will write and stays (as one stuck in Zenoh's teardown).
# It says so on the FIFO its argument names.
STUCK = [sys.executable, "-c", "import signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                               "open(sys.argv[1], 'w').write('ready\\n'); time.sleep(120)"]


@pytest.mark.slow
@pytest.mark.parametrize("finished", [True, False])
def test_a_recorder_that_does_not_leave_is_killed_and_its_file_decides_whether_the_recording_is_whole(
        tmp_path, monkeypatch, finished, fifo):
    monkeypatch.setattr(local, "RECORDER_STOP_S", 0.5)
    path = tmp_path / "day.mcap"
    writer = RecordingWriter(path, "stuck")
    writer.start({}, [])
    writer.write("dmosim/stuck/dmo/clock", b"{}", 1)
    writer.close() if finished else writer.flush()
    said: list[str] = []
    with Roles() as roles:
        role = roles.start("recorder", [*STUCK, str(fifo.path)], log=tmp_path / "recorder.log")
        assert fifo.line(role.process.pid) == "ready"  # SIGTERM ignored from now on
        failure = local._stop_recorder(roles, SimpleNamespace(say=said.append), [], path)
        assert role.process.poll() is not None  # killed, not left behind
    if finished:
        assert failure is None
        assert said and said[0].startswith("the recorder finished its file but then ")
    else:
        assert failure.startswith("did not finish its file within 0.5 s of being stopped") and not said


# A role that ignores SIGTERM and has started a process in a group of its own that ignores it too, as a `dmosim run`
# stuck on its way out has its roles: SIGKILL to the role's group alone would leave that one running.
# It names that process on the FIFO its argument names.
DEAF = [sys.executable, "-c", "import signal, subprocess, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                              "below = subprocess.Popen([sys.executable, '-c', 'import signal, time; "
                              "signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(120)'], process_group=0); "
                              "open(sys.argv[1], 'w').write(f'{below.pid}\\n'); time.sleep(120)"]


@pytest.mark.slow
def test_a_role_that_ignores_sigterm_is_killed_with_what_it_started_in_a_group_of_its_own(tmp_path, gone, fifo):
    below = None
    try:
        with Roles() as roles:
            role = roles.start("run", [*DEAF, str(fifo.path)], log=tmp_path / "run.log")
            below = int(fifo.line(role.process.pid))
            roles.stop_all(grace_s=0.5)
            assert role.process.poll() == -signal.SIGKILL and gone(below)
    finally:  # on a failure, nothing is left behind
        if below is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(below, signal.SIGKILL)


# --- roles forked from a pre-loaded host (dmosim run --hosting fork) ------------------------------------------

PROBE = """
import atexit, os, sys, time
print("argv", sys.argv[1:], "cwd", os.getcwd(), "env", os.environ.get("PROBE"), "ppid", os.getppid(),
      "pgid", os.getpgid(0), flush=True)
print("on stderr", file=sys.stderr, flush=True)
if os.environ.get("PROBE_SAYS"):  # a FIFO: where the test waits for it to be running
    open(os.environ["PROBE_SAYS"], "w").write(f"running {sys.argv[1:]}\\n")
atexit.register(print, "exit handlers ran")
if sys.argv[1] == "stay":
    time.sleep(120)
if sys.argv[1] == "boom":
    raise RuntimeError("boom")
sys.exit(int(sys.argv[1]) if sys.argv[1].isdigit() else sys.argv[1])
"""


def says(fifo) -> dict:
    """The environment of a probe that says on ``fifo`` that it runs."""
    return {**os.environ, "PROBE_SAYS": str(fifo.path)}


def probe(tmp_path: Path, *args: str) -> list[str]:
    """``python -m probe ARGS`` in ``tmp_path``: found there only if the child runs in that directory, as python -m
    puts it first on sys.path."""
    (tmp_path / "probe.py").write_text(PROBE)
    return [sys.executable, "-m", "probe", *args]


@pytest.mark.slow
def test_every_process_of_a_run_leads_a_group_of_its_own_in_the_launcher_s_session(tmp_path, fifo):
    """Not a session of its own: Linux shares the cores among sessions first (autogroup), which starved a host's
    hundreds of agents against the DMO and the routers (dmosim/launch/processes.py)."""
    with Roles() as roles:
        host = roles.fork_host(("json",), tmp_path / "host.log")
        started = [roles.start("alone", STAYS).process, host.process,
                   roles.start("forked", probe(tmp_path, "stay"), log=tmp_path / "forked.log", env=says(fifo),
                               cwd=tmp_path, host=host).process]
        assert fifo.line(started[2].pid) == "running ['stay']"
        for process in started:
            assert (os.getsid(process.pid), os.getpgid(process.pid)) == (os.getsid(0), process.pid)
            assert process.poll() is None


@pytest.mark.slow
def test_a_forked_role_runs_its_command_in_its_directory_environment_and_log_as_a_process_would(tmp_path):
    with Roles() as roles:
        host = roles.fork_host(("json",), tmp_path / "host.log")
        role = roles.start("mg1", probe(tmp_path, "3"), log=tmp_path / "mg1.log", env={**os.environ, "PROBE": "yes"},
                           cwd=tmp_path, host=host)
        assert roles.exits.get(timeout=60) == ("mg1", 3)
        assert role.process.returncode == 3
        for name, arg in (("mg2", "boom"), ("mg3", "bye")):
            roles.start(name, probe(tmp_path, arg), log=tmp_path / f"{name}.log", cwd=tmp_path, host=host)
            assert roles.exits.get(timeout=60) == (name, 1)  # an uncaught exception, SystemExit of a text
    log = (tmp_path / "mg1.log").read_text()
    assert f"argv ['3'] cwd {tmp_path.resolve()} env yes ppid {host.process.pid} pgid {role.process.pid}\n" in log
    assert "on stderr" in log and "exit handlers ran" in log
    assert "RuntimeError: boom" in (tmp_path / "mg2.log").read_text()
    assert "bye" in (tmp_path / "mg3.log").read_text()
    assert host.process.returncode == 0  # stopped with the roles


@pytest.mark.slow
def test_a_forked_role_is_restarted_killed_and_stopped_as_a_process_is(tmp_path, gone, fifo):
    with Roles() as roles:
        host = roles.fork_host(("json",), tmp_path / "host.log")
        log = tmp_path / "mg1.log"
        first = roles.start("mg1", probe(tmp_path, "stay"), log=log, env=says(fifo), cwd=tmp_path, host=host).process
        assert fifo.line(first.pid) == "running ['stay']"
        roles.restart("mg1")  # SIGKILL, then forked again with the same command, its log continued
        second = roles.roles["mg1"].process
        assert second.pid != first.pid and first.returncode == -signal.SIGKILL
        assert fifo.line(second.pid) == "running ['stay']"
        assert log.read_text().count("argv ['stay']") == 2  # its log continued
        roles.kill("mg1")
        assert roles.exits.get(timeout=60) == ("mg1", -signal.SIGKILL)  # the restart's exit was not reported
        stays = roles.start("mg2", probe(tmp_path, "stay"), log=tmp_path / "mg2.log", cwd=tmp_path, host=host).process
    assert stays.returncode == -signal.SIGTERM and gone(stays.pid)
    assert host.process.returncode == 0


@pytest.mark.slow
def test_a_host_that_dies_takes_its_roles_with_it_and_they_fail(tmp_path, gone):
    with Roles() as roles:
        host = roles.fork_host(("json",), tmp_path / "host.log")
        child = roles.start("mg1", probe(tmp_path, "stay"), log=tmp_path / "mg1.log", cwd=tmp_path, host=host).process
        os.killpg(host.process.pid, signal.SIGKILL)
        assert roles.exits.get(timeout=60) == ("mg1", -signal.SIGKILL)
        assert gone(child.pid)  # killed, not left running where nothing watches it
        with pytest.raises(RuntimeError, match="the agent host exited"):
            roles.start("mg2", probe(tmp_path, "0"), log=tmp_path / "mg2.log", cwd=tmp_path, host=host)


@pytest.mark.slow
def test_a_host_that_cannot_start_or_a_log_that_cannot_be_opened_is_an_error_at_start(tmp_path):
    with Roles() as roles:
        host = roles.fork_host(("no_such_module_here",), tmp_path / "host.log")
        with pytest.raises(RuntimeError, match="ModuleNotFoundError"):
            roles.start("mg1", probe(tmp_path, "0"), log=tmp_path / "mg1.log", cwd=tmp_path, host=host)
        host = roles.fork_host(("json",), tmp_path / "host2.log")
        with pytest.raises(OSError, match="cannot open"):
            roles.start("mg1", probe(tmp_path, "0"), log=tmp_path / "none" / "mg1.log", cwd=tmp_path, host=host)
        with pytest.raises(ValueError):
            roles.start("mg1", ["/bin/true"], host=host)
        roles.start("mg1", probe(tmp_path, "0"), log=tmp_path / "mg1.log", cwd=tmp_path, host=host)  # still serves
        assert roles.exits.get(timeout=60) == ("mg1", 0)


@pytest.mark.slow
def test_agents_sharing_a_forked_process_each_write_their_own_log_end_with_their_own_code_and_stop_together(
        tmp_path, gone, listener, capsys):
    run_id = "20260101T000000-abcdef"
    stay = ["agent", "--run-id", run_id, "--agents", "4", "--connect", f"tcp/127.0.0.1:{listener.port}",
            "--connect-timeout", "120"]  # the listener answers nothing: each keeps its connection, trying
    with Roles() as roles:
        host = roles.fork_host(("dmosim.cli.main",), tmp_path / "host.log")
        ended = roles.start_group(host, [("mg1", dmosim_command("--version"), tmp_path / "mg1.log"),
                                         ("mg2", dmosim_command("agent", "--id", "mg2"), tmp_path / "mg2.log")])
        assert {roles.exits.get(timeout=60) for _ in ended} == {("mg1", 0), ("mg2", 2)}
        assert ended[0].process.pid == ended[1].process.pid
        staying = roles.start_group(host, [(name, dmosim_command(*stay, "--id", name), tmp_path / f"{name}.log")
                                           for name in ("mg3", "mg4")])
        listener.accept()  # their process runs them: one is trying to reach its router (they open one at a time)
        with pytest.raises(ValueError, match="mg3 shares its process with 1 other"):
            roles.kill("mg3")
        with pytest.raises(ValueError, match="shares its process"):
            roles.restart("mg4")
    assert [r.process.returncode for r in staying] == [-signal.SIGTERM] * 2 and gone(staying[0].process.pid)
    # each log holds what its command said, as it says it when run here, and nothing of the other's
    with pytest.raises(SystemExit):
        main(["--version"])
    assert (tmp_path / "mg1.log").read_text() == capsys.readouterr().out
    assert main(["agent", "--id", "mg2"]) == 2
    assert (tmp_path / "mg2.log").read_text() == capsys.readouterr().err
    assert "mg4" not in (tmp_path / "mg3.log").read_text() and "mg3" not in (tmp_path / "mg4.log").read_text()


def test_what_an_agent_s_threads_print_and_log_goes_to_its_own_stream_named_after_it(monkeypatch):
    monkeypatch.setattr(threading.Thread, "start", threading.Thread.start)  # inherit() patches it: undone after
    fallback, mine = io.StringIO(), io.StringIO()
    streams = AgentStreams(fallback)
    streams.inherit()
    handler = logging.StreamHandler(streams)
    handler.addFilter(streams)
    handler.setFormatter(logging.Formatter("%(agent)s %(message)s"))
    log = logging.getLogger("test-agent-streams")
    log.addHandler(handler)
    monkeypatch.setattr(log, "propagate", False)

    def helper():  # a thread the agent starts, as its bid's delivery does
        log.warning("from its helper")
        print("printed by its helper", file=streams)

    def agent():
        streams.own("mg7", mine)
        log.warning("from the agent")
        started = threading.Thread(target=helper, name="delivery")
        started.start()
        started.join()
        streams.disown()  # as an agent's thread does as it ends

    for target, name in ((agent, "mg7-main"), (lambda: log.warning("from elsewhere"), "zenoh")):
        thread = threading.Thread(target=target, name=name)
        thread.start()
        thread.join()
    assert mine.getvalue() == "mg7 from the agent\nmg7 from its helper\nprinted by its helper\n"
    assert fallback.getvalue() == "zenoh from elsewhere\n"


def test_the_run_s_routers_stay_up_to_the_end_and_one_that_exits_fails_the_run():
    assert wait(told(("dmo", 0), ("mg1", 0), staying=("host1",)), routers=("host1",)) == ([], [])
    assert wait(told(("host2", 0), staying=("host1", "dmo")), routers=("host1", "host2")) == (["host2"], [])


def test_agents_are_spread_over_the_routers_in_blocks_of_consecutive_agents():
    agents = [f"mg{i}" for i in range(1, 8)]
    assert router_names(3) == ["host1", "host2", "host3"] and router_names(0) == []
    assert spread(agents, 3) == {"mg1": 0, "mg2": 0, "mg3": 0, "mg4": 1, "mg5": 1, "mg6": 2, "mg7": 2}
    assert set(spread(agents, 1).values()) == {0} and spread(agents[:2], 3) == {"mg1": 0, "mg2": 1}


def test_agents_are_grouped_in_the_run_s_order_and_those_a_fault_names_run_alone():
    agents = [(f"mg{i}", i) for i in range(1, 8)]
    assert groups(agents, 1, set()) == [[a] for a in agents]
    assert groups(agents, 3, {"mg2", "mg7"}) == [[("mg2", 2)], [("mg1", 1), ("mg3", 3), ("mg4", 4)], [("mg7", 7)],
                                                 [("mg5", 5), ("mg6", 6)]]
    assert groups(agents, 10, set()) == [agents]


def test_memory_is_resident_peak_and_proportional_share():
    mine = memory_mib(os.getpid())
    assert 0 < mine["pss_mib"] <= mine["rss_mib"] <= mine["peak_mib"]
