"""A run never ends quietly wrong, end to end with real processes: a tiny two-day run of one agent killed at hour 5,
whose recording ``dmosim info`` must count the meter data the DMO never had; then that recording run again
(``--from``) without the agent's fault and with the recorder killed mid-day: the days still settle, the tables of
every hour come from the DMO's journal, and the run exits 1 with one line naming the recorder and the statements
that differ, which ``result.json``'s verdict lists too."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pandas as pd
import pytest
from test_market_day import ENV, ROOT, TINY, dmosim

FIRST, SECOND = "2026-07-01", "2026-07-02"
QUICK = ["--agents", "1", "--days", "2", "--market-day", FIRST, "--subperiods", "1", *TINY,
         "--registration-timeout", "60", "--bid-timeout", "120", "--schedule-timeout", "120", "--hour-timeout", "60"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(dmosim(*args), capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)


@pytest.fixture(scope="module")
def killed(tmp_path_factory) -> tuple[Path, dict]:
    """Two days of mg1, killed at hour 5 of the first: a run without problems (exit 0) by the verdict's rules."""
    out_dir = tmp_path_factory.mktemp("killed")
    out = run("run", *QUICK, "--fault", "kill:mg1:5", "--out", str(out_dir), "--json", "--quiet")
    assert out.returncode == 0, out.stderr[-3000:]
    return out_dir, json.loads(out.stdout)


def test_a_killed_agent_is_no_problem_of_the_run_but_info_counts_its_missing_meter_data(killed):
    out_dir, result = killed
    assert result["verdict"] == {"ok": True, "problems": []} and result["recorded"]["complete"]
    info = json.loads(run("info", str(out_dir / "recording.mcap"), "--json").stdout)
    missing = {m["market_day"]: m for m in info["missing_meter"]}
    assert set(missing) == {FIRST, SECOND} and all(m["agent"] == "mg1" and m["settled"] for m in missing.values())
    # From the hour the kill landed to the day's end: `dmosim run` fires it once it hears the DMO's clock at hour 5,
    # and where hours take milliseconds it may hear it some hours late (docs/faults.md).
    first_missing = missing[FIRST]["hours"][0]
    assert first_missing >= 5 and missing[FIRST]["hours"] == list(range(first_missing, 25))
    assert missing[SECOND]["hours"] == list(range(1, 25))
    for d in result["days"]:  # as many sub-periods as the DMO settled by the missing-data rule
        assert sum(missing[d["market_day"]]["subperiods"]) == d["settlement"]["mg1"]["missing_subperiods"]
    text = run("info", str(out_dir / "recording.mcap")).stdout
    assert f"missing:     mg1 {SECOND}: no accepted meter report for hour(s) 1-24 (24 sub-period(s)), settled by " \
           "the missing-data rule (penalty in those hours: $" in text
    assert "missing:     nothing" not in text


def test_a_run_whose_recorder_dies_settles_every_day_from_the_journal_and_exits_1_saying_why(killed, tmp_path):
    source = killed[0] / "recording.mcap"
    out = run("run", "--from", str(source), "--fault", "kill:recorder:8", "--out", str(tmp_path), "--json",
              "--quiet")
    assert out.returncode == 1, out.stderr[-3000:]
    assert out.stderr.count("\n") == 1 and out.stderr.startswith("failed: the run is not to be trusted: "), out.stderr
    assert "the recorder failed: killed at day 1 realtime hour 8 (--fault kill:recorder:8)" in out.stderr
    assert f"--from {source}: " in out.stderr
    result = json.loads(out.stdout)
    assert json.loads((tmp_path / "result.json").read_text()) == result  # written with its verdict and comparison
    assert result["verdict"]["ok"] is False and len(result["verdict"]["problems"]) == 2
    assert [d["market_day"] for d in result["days"]] == [FIRST, SECOND]  # both days settled without the recorder
    recorded = result["recorded"]
    assert not recorded["complete"] and recorded["tables_from"] == "journal" and "kill:recorder:8" in recorded["recorder"]
    # this run's mg1 was never killed: every hour it missed before differs, and nothing else (each statement of
    # the run is there, from the journal)
    diffs = result["reproduced"]["differences"]
    assert not result["reproduced"]["identical"] and diffs
    assert all(re.match(rf"mg1 ({FIRST}|{SECOND}) hour \d+: ", line) for line in diffs), diffs
    assert len(diffs) == sum(d["settlement"]["mg1"]["missing_subperiods"] for d in killed[1]["days"])
    # the tables hold every hour of every day, adding up to what the DMO settled
    hours = pd.read_csv(tmp_path / "tables" / "hours.csv")
    assert hours.groupby("market_day")["hour"].apply(list).to_dict() == {d: list(range(1, 25)) for d in (FIRST, SECOND)}
    for d in result["days"]:
        own = hours[hours["market_day"] == d["market_day"]]
        assert own["total"].sum() == pytest.approx(d["settlement"]["mg1"]["total"], abs=0.01)
    assert len(pd.read_csv(tmp_path / "tables" / "meter.csv")) == 48
    assert (tmp_path / "run.png").read_bytes()[:4] == b"\x89PNG"


def test_the_docs_name_every_field_of_the_verdict_and_of_recorded_and_the_recorder_fault(killed):
    experiments = (ROOT / "docs" / "experiments.md").read_text()
    result = killed[1]
    for key in ["verdict", *result["verdict"], *result["recorded"]]:
        assert f"`{key}`" in experiments, key
    assert "| `kill:recorder:HOUR[:DAY]` |" in (ROOT / "docs" / "faults.md").read_text()
