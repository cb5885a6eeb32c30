"""A market day on a feeder, end to end: two agents at their buses of a five-bus feeder whose far line is rated low,
cleared with prices per bus, operated within the feeder's operating envelope, settled at each agent's own price and
again, to the cent, from the recording. The market runs in this process (``--in-process``), as do ``info`` and
``settle``; the day, its AC checks, tables and figure take about 12 s, so it is in the slow tier all the same."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from messages.recording import read_recording
from scenarios.case import DATA_DIR

TINY = ["--scenarios", "1", "--gap", "0.05"]


@pytest.mark.slow  # 12 s in this process
def test_a_day_on_a_feeder_prices_each_bus_and_settles_again_from_the_recording(tmp_path, cli):
    # feeder5 with its far line 2-3 rated 0.5 MVA: an agent at bus 3 importing more than the line's room congests it
    feeder = (DATA_DIR / "feeder5.toml").read_text().replace("s_max_mva = 3.0", "s_max_mva = 0.5")
    (tmp_path / "feeder.toml").write_text(feeder)
    (tmp_path / "fleet.toml").write_text('[[agents]]\nid = "near"\nbus = "1"\n\n[[agents]]\nid = "far"\nbus = "3"\n')
    (tmp_path / "e.toml").write_text('[agents]\nfleet = "fleet.toml"\n[network]\nfeeder = "feeder.toml"\n')
    out = tmp_path / "run"
    done = cli("run", str(tmp_path / "e.toml"), "--subperiods", "1", *TINY, "--settlement", "price-linked",
               "--in-process", "--out", str(out), "--json", "--quiet")
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout)

    rec = read_recording(result["recording"])
    awards = {msg.agent: msg for _, msg in rec.decoded("award")}
    assert (awards["near"].bus, awards["far"].bus) == ("1", "3")
    for award in awards.values():  # each price is its components' sum, the losses' among them (the AC clearing)
        assert any(award.loss_price_per_mwh)
        for h in range(24):
            parts = (award.energy_price_per_mwh[h] + award.loss_price_per_mwh[h] + award.congestion_price_per_mwh[h]
                     + award.voltage_price_per_mwh[h])
            assert abs(parts - award.clearing_price_per_mwh[h]) < 1e-6
    far, near = (awards[a] for a in ("far", "near"))
    line = [h for h in range(24) if result["congestion"][h] == "line"]
    assert any(far.clearing_price_per_mwh[h] != near.clearing_price_per_mwh[h] for h in line), "prices never separated"
    for h in range(24):  # the energy price is the substation's, the same for both: only the local parts differ
        assert far.energy_price_per_mwh[h] == near.energy_price_per_mwh[h]
        local = [a.loss_price_per_mwh[h] + a.congestion_price_per_mwh[h] + a.voltage_price_per_mwh[h]
                 for a in (far, near)]
        assert abs(far.clearing_price_per_mwh[h] - near.clearing_price_per_mwh[h] - (local[0] - local[1])) < 1e-6
    hours = pd.read_csv(out / "tables" / "hours.csv", dtype={"bus": str})
    settled_far = hours[hours["agent"] == "far"].set_index("hour")
    assert (settled_far["bus"] == "3").all()
    assert list(settled_far["clearing_price_per_mwh"]) == pytest.approx(far.clearing_price_per_mwh, abs=1e-9)  # its own

    # each hour's grid state carries the rooms of every bus, and each agent meters within its award less its bus's
    # export room and plus its import room in every connected sub-period, but in the hours it said it could not
    # (counted in its agent_day); behind the congested line the far bus has no import room but export room
    grids = {msg.hour: msg for _, msg in rec.decoded("grid_state")}
    assert sorted(grids) == list(range(1, 25))
    assert all(g.buses == ("0", "1", "2", "3", "4") and len(g.import_room_mw) == len(g.export_room_mw) == 5
               for g in grids.values())
    assert any(grids[h + 1].import_room_mw[3] == 0 < grids[h + 1].export_room_mw[3] for h in line)
    assert any(g.import_room_mw[1] > 0 for g in grids.values())
    fallbacks = {msg.sender: msg.messages.ignored.get("envelope_infeasible", 0) for _, msg in rec.decoded("agent_day")}
    assert set(fallbacks) == {"near", "far"}
    for _, report in rec.decoded("meter_report"):
        award, grid = awards[report.sender], grids[report.hour]
        j, p_sch = grid.buses.index(award.bus), award.p_sch_mw[report.hour - 1]
        outside = [not p_sch - grid.export_room_mw[j] - 1e-9 <= p <= p_sch + grid.import_room_mw[j] + 1e-9
                   for p, connected in zip(report.p_m_mw, grid.connected) if connected]
        if any(outside):
            fallbacks[report.sender] -= 1
    assert min(fallbacks.values()) >= 0, fallbacks  # no agent strayed from its envelope more often than it said

    # the feeder as planned and as realised, each hour with its AC check, in the recording and the tables
    stages = [(msg.stage, msg.hour) for _, msg in rec.decoded("network_hour")]
    assert sorted(stages) == sorted([(s, h) for s in ("plan", "realised") for h in range(1, 25)])
    network = pd.read_csv(out / "tables" / "network.csv")
    assert len(network) == 48 and network["ac_converged"].all()
    assert (network["ac_voltage_error_pu"] < 0.02).all()
    assert len(pd.read_csv(out / "tables" / "buses.csv")) == 48 * 5
    # what binds: in each hour labelled "line", line 2-3's facet at a limit loading of 1 with a positive shadow price
    lines = pd.read_csv(out / "tables" / "lines.csv")
    held = lines[(lines["stage"] == "plan") & lines["binding_facet"].notna()]
    assert {h + 1 for h in line} <= set(held.loc[held["line"] == "2-3", "hour"])
    assert ((held["limit_loading"] - 1).abs() < 1e-6).all() and (held["line_shadow_price_per_mwh"] > 0).all()
    assert lines.loc[lines["stage"] == "realised", "binding_facet"].isna().all()
    assert result["figure"].endswith("run.png") and (out / "run.png").read_bytes()[:4] == b"\x89PNG"  # feeder row too

    info = cli("info", result["recording"]).stdout
    assert "feeder:      feeder5 (5 buses): far at bus 3, near at bus 1\n" in info

    settled = json.loads(cli("settle", result["recording"], "--json").stdout)
    assert settled["identical"], settled
