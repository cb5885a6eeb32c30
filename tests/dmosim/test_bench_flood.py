"""The flood bench end to end on a short flood: its figures are all there, the flooder sent every pattern, the
verbs ran on the flooded recording, and nothing it started is left running. No figure is asserted."""

from __future__ import annotations

import json
import os

import pytest

from dmosim.bench.flood import FLOOD_PATTERNS
from dmosim.cli import main
from dmosim.launch.processes import descendants


@pytest.mark.slow
def test_a_short_flood_is_measured_beside_the_honest_day_and_its_recording_still_reads(capsys, tmp_path):
    assert main(["bench", "flood", "--agents", "2", "--flood", "5", "--out", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    honest, flooded = out["runs"]
    assert (honest["run"], flooded["run"]) == ("honest", "flooded")
    for row in (honest, flooded):
        assert row["wall_s"] > 0 and row["dmo_peak_mib"] > 0 and row["journal_mib"] > 0 and row["recording_mib"] > 0
        assert row["agents_exit"] == "0,0" and row["recorder_exit"] == 0
    assert honest["rejected"] == 0 < flooded["rejected"]
    assert out["flood"]["token_learned"] and 0 < out["flood"]["flooded_s"]
    assert [p["pattern"] for p in out["flood"]["patterns"]] == list(FLOOD_PATTERNS)
    assert all(p["puts"] > 0 for p in out["flood"]["patterns"])
    assert out["flood"]["reached_dmo"] > 0 and out["flood"]["link_closed"] >= 0
    assert [h["selector"] for h in out["flood"]["history"]] == ["dmo/clock?history", "**?history"]
    assert all(h["queries"] >= h["answered"] + h["refused"] + h["unanswered"] for h in out["flood"]["history"])
    assert [(v["verb"], v["exit"]) for v in out["verbs"]] == [("info", 0), ("settle", 0), ("export", 0)]
    assert out["verbs"][1]["identical"] is True
    assert set(out["bills"]["totals honest, flooded"]) == {"mg1", "mg2"}
    assert len(out["goals"]) == 6 and all(isinstance(g["met"], bool) for g in out["goals"])
    assert set(out["ratios"]) >= {"wall flooded / honest", "dmo peak flooded / honest"}
    assert (tmp_path / "flooded" / "flood.json").is_file() and (tmp_path / "flooded" / "tables").is_dir()
    assert descendants(os.getpid()) == [(os.getpid(), 0)]  # every role, the flooder and the verbs are gone
