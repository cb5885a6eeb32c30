"""The Python API's examples (docs/api.md) run as a user runs them, and print what they promise."""

from __future__ import annotations

import json
import subprocess
import sys

from test_market_day import ENV, ROOT, dmosim

from dmosim.cli.info import describe, render
from messages.recording import read_recording

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


def test_strategy_bids_its_own_way_is_registered_by_name_and_a_rerun_must_trust_it(tmp_path):
    """examples/strategy.py: one tiny agent for two days; its registration names the strategy, the second day's bid
    (prices pulled halfway to the first day's clearing prices) is not the first's; and ``run --from`` that run
    refuses to load the strategy the recording names, unless the user names it or trusts the recording."""
    lines = run_example("strategy.py", str(tmp_path / "run")).stdout.splitlines()
    assert lines[0] == f"mg1 registered, bidding with {EXAMPLES / 'strategy.py'}:Shaded:shade=0.5"
    first, second = (line.split(": mg1 bid ")[1] for line in lines[1:3])
    assert lines[1].startswith("2026-07-06: ") and lines[2].startswith("2026-07-07: ") and first != second
    info = render(describe(read_recording(tmp_path / "run" / "recording.mcap")))
    assert f"strategies:  mg1 {EXAMPLES / 'strategy.py'}:Shaded:shade=0.5\n" in info

    def rerun(*flags):
        return subprocess.run(dmosim("run", "--from", str(tmp_path / "run"), "--check", *flags), capture_output=True,
                              text=True, timeout=300, cwd=ROOT, env=ENV)
    refused = rerun()
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert (f"its experiment names the strategy {EXAMPLES / 'strategy.py'}:Shaded:shade=0.5 for mg1, a strategy of "
            "the recording's own, which dmosim does not run unless you name it yourself (--strategy") in refused.stderr
    trusted = rerun("--trust-rules")  # naming it yourself (--strategy) is tests/dmosim/test_strategy_choice.py's
    assert trusted.returncode == 0 and "inputs are valid" in trusted.stdout, trusted.stderr


def test_islanding_rule_waives_only_the_islanded_sub_periods_on_the_trial_day():
    lines = run_example("islanding_rule.py").stdout.splitlines()
    assert lines[0].startswith("paper ") and "islanding_exempt" in lines[1]
    assert "mg1 $1181.25" in lines[1]  # mg1 imports: P_M = 0 below its award costs nothing under the paper rule either
