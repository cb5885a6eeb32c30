"""The logical clock at the scale and on the machine a user has (docs/experiments.md, "Logical and wall-clock time"):
sixty agents with every setting its default, and the feeder example beside two busy loops, end verdict ok, where
importing their solver stacks side by side once outlasted the registration deadline; and an agent that dies before
it registers fails the run at once, naming it, instead of leaving the DMO to wait for it."""

from __future__ import annotations

import json
import tomllib

import pytest

from test_market_day import ENV, ROOT, dmosim, ended

pytestmark = pytest.mark.slow


def test_sixty_agents_with_the_defaults_end_verdict_ok(tmp_path):
    out = ended(dmosim("run", "--agents", "60", "--scenarios", "1", "--subperiods", "1", "--out",
                       str(tmp_path / "run"), "--json", "--quiet"),
                timeout=1200, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert result["verdict"]["ok"] and len(result["settlement"]) == 60
    assert all(s["missing_subperiods"] == 0 for s in result["settlement"].values())
    # auto hosting forked them, and the run directory's experiment says how
    agents = tomllib.loads((tmp_path / "run" / "experiment.toml").read_text())["agents"]
    assert (agents["hosting"], agents["per_process"]) == ("fork", 8)


def test_the_feeder_example_ends_verdict_ok_with_both_cores_busy(tmp_path, busy_cores):
    with busy_cores():
        out = ended(dmosim("run", str(ROOT / "examples" / "feeder.toml"), "--days", "1", "--scenarios", "1",
                           "--subperiods", "1", "--out", str(tmp_path / "run"), "--json", "--quiet"),
                    timeout=1800, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout)["verdict"]["ok"]


STRATEGY = '''
import os, sys

class DiesAtStart:
    """Exits its agent's process as the agent makes it (before the agent joins); harmless where it is checked."""

    def __init__(self):
        if "agent" in sys.argv:
            os._exit(3)

    def bids(self, call, microgrid):
        return ((),) * 24
'''


def test_an_agent_that_dies_before_it_registers_fails_the_run_at_once_naming_it(tmp_path):
    (tmp_path / "dies.py").write_text(STRATEGY)
    fleet = tmp_path / "fleet.toml"
    fleet.write_text('[[agents]]\nid = "mg1"\ncase = "paper"\n\n[[agents]]\nid = "mg2"\ncase = "paper"\n'
                     f'strategy = "{tmp_path / "dies.py"}:DiesAtStart"\n')
    out = ended(dmosim("run", "--fleet", str(fleet), "--scenarios", "1", "--subperiods", "1", "--out",
                       str(tmp_path / "run"), "--json", "--quiet"),
                timeout=600, cwd=ROOT, env=ENV)
    last = out.stderr.splitlines()[-1]
    assert out.returncode == 1 and "mg2" in last and "exit 3" in last and "mg1" not in last, out.stderr
    assert not (tmp_path / "run" / "result.json").exists()  # no day was settled: the DMO never got past registration
