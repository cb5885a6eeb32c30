"""The Python API's examples (docs/api.md) run as a user runs them, and print what they promise."""

from __future__ import annotations

import json
import subprocess
import sys

from test_market_day import ENV, ROOT

EXAMPLES = ROOT / "examples"


def run_example(name: str, *args: str) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True, timeout=600,
                         cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:] + out.stdout[-3000:]
    return out


def test_solve_one_solves_checks_and_shows_a_schedule():
    out = run_example("solve_one.py").stdout
    assert "checked: every constraint holds" in out and "unit commitment" in out and "load_shed" in out


def test_market_days_runs_two_days_and_reads_them_as_tables(tmp_path):
    out = run_example("market_days.py", str(tmp_path / "run")).stdout
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    assert [d["market_day"] for d in result["days"]] == ["2026-07-06", "2026-07-07"]
    assert f"run {result['run_id']}" in out and "2026-07-07" in out.split("each agent's bill per day")[1]
    for agent, days in result["realised"].items():
        assert [d["day"] for d in days] == [1, 2] and f"{agent}: own operating cost" in out


def test_settlement_rule_settles_a_day_under_the_paper_rule_and_its_capped_variant():
    lines = run_example("settlement_rule.py").stdout.splitlines()
    assert lines[0].startswith("paper ") and "capped_penalty:cap=20" in lines[1]
    assert "mg1 $20.00, mg2 $20.00, mg3 $20.00" in lines[1]
