"""Several market days end to end: ``dmosim run --days 2`` as real processes under a settlement rule other than the
paper's, the DMO killed and restarted on the second day, every day settled again from the recording under the
same rule, and each agent carrying its microgrid across midnight (units in their state for their minimum up/down
times, storage at its energy)."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pandas as pd
from test_market_day import DEADLINES, ENV, ROOT, TINY, dmosim, ended

from messages.recording import read_recording
from scenarios.case import load_case
from scenarios.days import hours_in_state

FIRST, SECOND = "2026-07-06", "2026-07-07"
RULE = "deadband:below_rate=40,band_mw=0.2"  # not the paper's rule: settled live and again under the same one


def test_two_days_carry_over_midnight_survive_a_dmo_restart_and_settle_from_the_recording(tmp_path):
    argv = dmosim("run", "--agents", "2", "--days", "2", "--market-day", FIRST, "--subperiods", "1", *TINY,
                  *DEADLINES, "--seed", "4", "--load-scale", "1,0.8", "--fault", "restart:dmo:5:2",
                  "--fault", "delay:agent/*/meter:0.6",  # hour 5's reports are on their way when the DMO dies
                  "--settlement", RULE, "--out", str(tmp_path), "--json", "--quiet")
    out = ended(argv, timeout=900, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert [d["market_day"] for d in result["days"]] == [FIRST, SECOND] and result["restarts"] == {"dmo": 1}
    (resumed,) = [i for i in result["incidents"] if "resumed" in i["reason"]]
    assert resumed["market_day"] == SECOND and resumed["hour"] == 5
    memory = result["memory_mib"]  # each role's memory as each day's last hour starts
    assert set(memory) == {"1", "2"} and {"dmo", "mg1", "mg2", "recorder"} <= set(memory["2"])
    assert all(0 < m["rss_mib"] <= m["peak_mib"] for m in memory["2"].values())
    for agent, s in result["settlement"].items():  # the run's totals are its days' sums
        assert round(sum(d["settlement"][agent]["total"] for d in result["days"]), 2) == s["total"]

    # the recording settles each day again, to the cent, and its tables hold both days
    settled = json.loads(subprocess.run(dmosim("settle", result["recording"], "--json"), capture_output=True,
                                        text=True, timeout=120, cwd=ROOT, env=ENV).stdout)
    assert settled["identical"] and settled["market_days"] == [FIRST, SECOND]
    for day, again in zip(result["days"], settled["days"]):
        assert again["totals"] == {a: s["total"] for a, s in day["settlement"].items()}
    recording = read_recording(result["recording"])
    named = "deadband:rate=150,below_rate=40,band_mw=0.2,band_share=0.1"
    assert {msg.settlement_rule for _, msg in recording.decoded("settlement_statement")} == {named}
    assert all(msg.settlement_rule == named and msg.deviation_cost is not None for _, msg in recording.decoded("award"))
    hours = pd.read_csv(tmp_path / "tables" / "hours.csv")
    assert hours.groupby("market_day").size().to_dict() == {FIRST: 48, SECOND: 48}

    # across midnight: each agent's day 2 started where its day 1 ended
    schedules = {(msg.market_day, msg.sender): msg for _, msg in recording.decoded("schedule")}
    case = load_case("paper")
    realised = {(msg.market_day, msg.sender): msg for _, msg in recording.decoded("agent_day")}  # as the agents said
    for agent in result["agents"]:
        units = realised[FIRST, agent].units
        day1, day2 = (np.array([schedules[day, agent].commitment[u.name] for u in case.units]) for day in (FIRST, SECOND))
        assert [units[u.name].on for u in case.units] == [bool(x) for x in day1[:, -1]]
        assert [units[u.name].hours for u in case.units] == list(hours_in_state(day1))
        assert realised[FIRST, agent].stored_mwh is not None
        assert [d["market_day"] for d in result["realised"][agent]] == [FIRST, SECOND]  # the DMO took both days
        for unit, on, row in zip(case.units, day1[:, -1], day2):
            keep = max(0, (unit.min_up if on else unit.min_down) - units[unit.name].hours)
            assert (row[:keep] == on).all(), f"{agent} {unit.name}: day 2 broke its minimum up/down time"
