"""``dmosim sweep`` end to end: two variants of a tiny experiment run side by side as real ``dmosim run``s (each
market in its run's one process: what is tested is the sweep, not the market's processes), and the sweep's table
holds each agent's bill exactly as each run's own result says; one of them run again from its recording (``dmosim
run --from``) settles to the cent as before, and the other variant is told apart."""

from __future__ import annotations

import json
import subprocess

import pandas as pd
from test_market_day import ENV, ROOT, dmosim, ended

from dmo.replay.reproduce import differences
from messages.recording import read_recording

EXPERIMENT = """name = "tiny"
market_day = "2026-07-01"
[agents]
count = 1
hosting = "in-process"
[market]
subperiods = 1
[schedule]
scenarios = 1
gap = 0.05
time_limit = 60.0
[deadlines]
bid = 120.0
schedule = 120.0
hour = 60.0
"""


def test_a_sweep_runs_each_variant_and_tables_every_bill(tmp_path):
    (tmp_path / "tiny.toml").write_text(EXPERIMENT)
    out = ended(dmosim("sweep", str(tmp_path / "tiny.toml"), "--set", "market.penalty=0,400",
                       "--parallel", "2", "--out", str(tmp_path / "sweep"), "--json"),
                timeout=600, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    summary = json.loads(out.stdout)
    assert summary["runs"] == 2 and summary["failed"] == [] and summary["keys"] == ["market.penalty"]
    assert "2/2 runs (100%), done" in out.stderr
    table = pd.read_csv(summary["table"])
    assert list(table["market.penalty"]) == [0, 400] and set(table["status"]) == {"ok"}
    for _, row in table.iterrows():
        run = tmp_path / "sweep" / row["label"]
        assert json.loads((run / "result.json").read_text())["settlement"][row["agent"]]["total"] == row["total"]
        assert f"penalty = {float(row['market.penalty'])!r}" in (run / "experiment.toml").read_text()
    assert table.loc[0, "deviation_penalty"] == 0  # no penalty rate, no penalty
    assert (table["wall_s"] > 0).all() and (table["curtailment_mwh"] >= 0).all()
    assert (table["operating_cost"] > 0).all()  # the agent's own generation, from its realised days
    assert (tmp_path / "sweep" / "sweep.png").read_bytes()[:4] == b"\x89PNG"

    first, second = (tmp_path / "sweep" / label / "recording.mcap" for label in table["label"])
    again = subprocess.run(dmosim("run", "--from", str(first.parent), "--out", str(tmp_path / "again"), "--json",
                                  "--quiet"), capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads(again.stdout)["reproduced"] == {"source": str(first), "identical": True, "differences": []}
    told_apart = differences(read_recording(first), read_recording(second))  # penalty 0 against 400
    assert told_apart and all(line.startswith("mg1 2026-07-01 hour ") for line in told_apart)
