"""How agents are hosted changes nothing the market sees: the same tiny day run with each agent a process of its own
and with the agents forked from one pre-loaded host (``dmosim run --hosting``, docs/benchmarks.md "Hosting agents"),
both with the same kill fault, settles every agent to the cent alike."""

from __future__ import annotations

import json
import os
import signal
import subprocess

from test_market_day import DEADLINES, ENV, ROOT, TINY, dmosim

from dmo.replay.reproduce import differences
from messages.recording import read_recording

# mg2's meter reports held back 3 s by its own Bus: the one of the hour it is killed in is still held when the
# SIGKILL lands (the launcher fires it as the clock reaches that hour), so both runs lose exactly the same reports.
FAULTS = ["kill:mg2:2", "delay:agent/mg2/meter:3"]


def test_forked_agents_settle_to_the_cent_as_agent_processes_and_a_killed_one_is_settled_as_missing(tmp_path):
    common = ["run", "--agents", "2", "--subperiods", "1", *TINY, *DEADLINES, "--json", "--quiet", "--seed", "4",
              *[flag for f in FAULTS for flag in ("--fault", f)]]
    runs = {hosting: subprocess.Popen(dmosim(*common, "--hosting", hosting, "--out", str(tmp_path / hosting)),
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV,
                                      start_new_session=True)
            for hosting in ("process", "fork")}
    try:
        out = {hosting: p.communicate(timeout=600) for hosting, p in runs.items()}
    finally:
        for p in runs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    for hosting, p in runs.items():
        assert p.returncode == 0, f"{hosting}: {out[hosting][1][-3000:]}"
    process, fork = (json.loads(out[hosting][0]) for hosting in ("process", "fork"))

    assert differences(read_recording(process["recording"]), read_recording(fork["recording"])) == []
    assert process["settlement"] == fork["settlement"] and process["awards"] == fork["awards"]
    # the kill fault fired in the forked run as in the other: mg2 reported hour 1 only, and vanished
    assert fork["settlement"]["mg2"]["missing_subperiods"] == 23 and fork["settlement"]["mg1"]["missing_subperiods"] == 0
    assert any(i["agent"] == "mg2" and "vanished" in i["reason"] for i in fork["incidents"])
    # the agents were forked from the host in one run, and there was no host in the other
    assert "_host" in fork["memory_mib"]["1"] and "_host" not in process["memory_mib"]["1"]
    assert (tmp_path / "fork" / "logs" / "_host.log").is_file() and "mg1 registered" in (
        tmp_path / "fork" / "logs" / "mg1.log").read_text()
