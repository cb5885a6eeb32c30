"""How agents are hosted changes nothing the market sees: the same tiny day run with each agent a process of its own,
with the agents forked from one pre-loaded host, and with two of them sharing one forked process (``dmosim run
--hosting``, ``--per-process``, docs/benchmarks.md "Hosting agents"), all with the same kill fault, settles every agent
to the cent alike."""

from __future__ import annotations

import json
import subprocess

from test_market_day import DEADLINES, ENV, ROOT, TINY, dmosim, kill_session

from dmo.replay.reproduce import differences
from messages.recording import read_recording

# mg2's meter reports held back 3 s by its own Bus: the one of the hour it is killed in is still held when the
# SIGKILL lands (the launcher fires it as the clock reaches that hour), so both runs lose exactly the same reports.
FAULTS = ["kill:mg2:2", "delay:agent/mg2/meter:3"]


def test_forked_agents_settle_to_the_cent_as_agent_processes_and_a_killed_one_is_settled_as_missing(tmp_path):
    common = ["run", "--agents", "3", "--subperiods", "1", *TINY, *DEADLINES, "--json", "--quiet", "--seed", "4",
              *[flag for f in FAULTS for flag in ("--fault", f)]]
    hostings = {"process": ["--hosting", "process"], "fork": ["--hosting", "fork"],
                "shared": ["--hosting", "fork", "--per-process", "2"]}  # mg2, killed, alone; mg1 and mg3 together
    runs = {name: subprocess.Popen(dmosim(*common, *flags, "--out", str(tmp_path / name)), stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV, start_new_session=True)
            for name, flags in hostings.items()}
    try:
        out = {hosting: p.communicate(timeout=600) for hosting, p in runs.items()}
    finally:
        for p in runs.values():
            if p.poll() is None:  # every process of its session: its roles lead process groups of their own
                kill_session(p.pid)
                p.wait()
    for hosting, p in runs.items():
        assert p.returncode == 0, f"{hosting}: {out[hosting][1][-3000:]}"
    process, fork, shared = (json.loads(out[hosting][0]) for hosting in hostings)

    for other in (fork, shared):
        assert differences(read_recording(process["recording"]), read_recording(other["recording"])) == []
        assert process["settlement"] == other["settlement"] and process["awards"] == other["awards"]
    # the kill fault fired in the forked run as in the other: mg2 reported hour 1 only, and vanished
    assert fork["settlement"]["mg2"]["missing_subperiods"] == 23 and fork["settlement"]["mg1"]["missing_subperiods"] == 0
    assert any(i["agent"] == "mg2" and "vanished" in i["reason"] for i in fork["incidents"])
    # the agents were forked from the host in one run, and there was no host in the other
    assert "_host" in fork["memory_mib"]["1"] and "_host" not in process["memory_mib"]["1"]
    assert (tmp_path / "fork" / "logs" / "_host.log").is_file()
    assert (tmp_path / "fork" / "logs" / "mg1.log").stat().st_size > 0  # each agent its own log
    # mg1 and mg3 shared one process, each counting its own CPU: never more than the time it computed (the process's
    # counted, in the one that waited for its turn, what the other computed meanwhile)
    for agent in ("mg1", "mg3"):
        (day,) = shared["realised"][agent]
        for e in day["compute"]:
            assert e["cpu_s"] <= e["wall_s"] - e["turn_s"] + 0.01, (agent, e)
    # and each wrote its own log and counted half of the process's PSS
    memory = shared["memory_mib"]["1"]
    assert memory["mg1"] == memory["mg3"]  # one process sampled once (mg2, killed, is gone by then)
    for agent, other in (("mg1", "mg3"), ("mg3", "mg1")):
        log = (tmp_path / "shared" / "logs" / f"{agent}.log").read_text()
        assert f" {agent} " in log and other not in log  # its lines name it, and none the other
