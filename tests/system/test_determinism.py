"""A run is a function of its experiment (docs/experiments.md, "Logical and wall-clock time"): one small experiment (2
agents, 2 days, a feeder, message faults) run on the logical clock gives the same awards, statements and every
recorded message of the market, apart from each message's envelope (its run token, sender process, number and
time), with both cores loaded by busy loops, with the agents forked instead of processes, on three routers instead
of one, and with the whole market in one process (which has no network to lose messages on: it runs without the
message faults, and gives what the processes gave with them)."""

from __future__ import annotations

import json

import pytest

from test_market_day import ENV, ROOT, dmosim, ended
from messages.recording import read_recording

pytestmark = pytest.mark.slow

MARKET = ["--agents", "2", "--days", "2", "--feeder", "feeder5", "--scenarios", "1", "--subperiods", "1", "--gap",
          "0.05", "--seed", "11", "--market-day", "2026-07-01"]
EXPERIMENT = [*MARKET, "--fault", "drop:agent/*/meter:0.1", "--fault", "duplicate:dmo/grid:1",
              "--fault", "delay:agent/mg2/bid:0.5"]
# what the market said and was told; an agent's own account of its day (its computation's seconds) is not here
KINDS = ("registration", "call_for_bids", "bid", "award", "schedule", "network_hour", "grid_state", "meter_report",
         "settlement_statement", "day_summary")
ENVELOPE = {"seq", "sent_at", "run", "incarnation"}


def run(tmp_path, name: str, *flags: str, experiment=EXPERIMENT) -> dict:
    out = ended(dmosim("run", *experiment, *flags, "--out", str(tmp_path / name), "--json", "--quiet"),
                timeout=900, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout)


def market(result: dict) -> dict:
    """The run's awards and statements, and each kind of recorded message without its envelope (each distinct
    content once: a copy sent again is the same message)."""
    rec = read_recording(result["recording"])
    said = {kind: sorted({json.dumps(msg.model_dump(mode="json", exclude=ENVELOPE), sort_keys=True)
                          for _, msg in rec.decoded(kind)}) for kind in KINDS}
    return {"awards": result["awards"], "prices": result["clearing_prices"], "settlement": result["settlement"],
            "said": said}


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    result = run(tmp_path_factory.mktemp("base"), "base", "--hosting", "process", "--routers", "1")
    assert result["verdict"]["ok"], result["verdict"]
    out = market(result)
    assert all(out["said"].values()) and len(out["said"]["settlement_statement"]) == 4
    return out


def test_both_cores_busy_change_nothing(base, tmp_path, busy_cores):
    with busy_cores():
        again = run(tmp_path, "busy", "--hosting", "process", "--routers", "1")
    assert market(again) == base


def test_forked_agents_change_nothing(base, tmp_path):
    assert market(run(tmp_path, "fork", "--hosting", "fork", "--routers", "1")) == base


def test_three_routers_change_nothing(base, tmp_path):
    assert market(run(tmp_path, "mesh", "--hosting", "process", "--routers", "3")) == base


def test_one_process_changes_nothing(base, tmp_path):
    assert market(run(tmp_path, "one", "--hosting", "in-process", experiment=MARKET)) == base
