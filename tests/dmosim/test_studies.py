"""The studies of Section IV on tiny instances (1 sub-period/h, 1 scenario): frame shapes and the properties the
model guarantees (cost monotone in H, in c and in the award), which hold whatever the scenarios, and the ``dmosim
study`` command end to end (2 scenarios, slow)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from dmosim.cli import main
from dmosim.cli.solve import solve_verified
from dmosim.studies import paper as studies
from microgrid_agent.instance import make_instance
from scenarios.case import load_case

REPO = Path(__file__).resolve().parents[2]
GAP = 0.01
ARGS = SimpleNamespace(gap=GAP, time_limit=120.0, method="auto", workers=1)
CASE = load_case("paper")
HOURS = list(range(1, 25))


def make(**overrides):
    # sample_size = scenarios: no reduction, so every sweep sees exactly the same scenarios (with reduction the
    # kept subset may change with H, and Fig. 2's monotonicity holds only up to that change)
    settings = dict(scenarios=1, subperiods=1, sample_size=1, seed=0) | overrides
    return make_instance(CASE, **settings)


def solve(inst, label):
    return solve_verified(inst, ARGS, label)  # every study solve also passes the independent checker


def assert_monotone(costs, increasing: bool):
    tol = GAP * max(abs(c) for c in costs)
    steps = np.diff(costs) if increasing else -np.diff(costs)
    assert (steps >= -tol).all(), costs


def test_paper_table2_as_printed():
    paper = studies.paper_table2()
    on, bold = paper.loc["paper"][HOURS], paper.loc["paper_bold"][HOURS]
    assert on.shape == bold.shape == (4, 24)
    assert on.loc["G1"].sum() == on.loc["G2"].sum() == 24
    assert on.loc["G3"].tolist() == [1, 1, 1, 1, 1, 0, 0] + [1] * 15 + [0, 0]
    assert [h for h in HOURS if on.loc["G4", h]] == list(range(13, 20))  # padded: 23-24 off
    assert bold.to_numpy().sum() == 2 + 6 + 7
    assert "22 entries" in paper.loc[("paper", "G4"), "note"]


def test_table2():
    """Table II against what the model must do, worked out from the case alone: in the islanded hour (U = 0, no
    import) balance (2) leaves the fixed load less the renewables and the storage's largest discharge (8) to the
    committed units, or to shedding at VOLL, which one more unit avoids; G1 is on all day, as the paper prints it;
    and the bold entries are exactly where islanding changed the commitment, the islanded hour among them."""
    frames = studies.table2(make, solve)
    ours = frames["table2"]
    with_islanding, without, changed = (ours.loc[c][HOURS] for c in ("island_1h", "no_islanding", "changed"))
    assert with_islanding.shape == (4, 24) and list(with_islanding.index) == ["G1", "G2", "G3", "G4"]
    assert set(np.unique(with_islanding)) <= {0, 1}
    assert (changed == (with_islanding != without).astype(int)).all().all()

    inst = make(island_hours=1, penalty=math.inf)
    [islanded] = [h for h in HOURS if not inst.scen.connected[0][h - 1]]
    need = inst.scen.load[0][islanded - 1] - sum(r[0][islanded - 1] for r in inst.scen.renewable) \
        - CASE.storage.p_dch_max
    p_max = {unit.name: unit.p_max for unit in CASE.units}
    committed = {case: sum(p_max[u] * on.loc[u, islanded] for u in p_max) for case, on in
                 (("island_1h", with_islanding), ("no_islanding", without))}
    assert committed["island_1h"] >= need > p_max["G1"]  # islanded, G1 alone would shed load
    assert committed["no_islanding"] < need  # connected, the grid carries what the units need not
    assert changed[islanded].sum() >= 1
    assert (with_islanding.loc["G1"] == 1).all() and (without.loc["G1"] == 1).all()


def test_table2_agreement_counts_the_unit_hours_equal_to_the_printed_table():
    """Our table made from the paper's own, then three unit-hours and two bold marks changed by hand."""
    paper = studies.paper_table2()
    on, bold = paper.loc["paper"][HOURS].copy(), paper.loc["paper_bold"][HOURS].copy()
    on.loc["G4", 1] = 1 - on.loc["G4", 1]
    on.loc["G3", 6] = 1 - on.loc["G3", 6]
    on.loc["G1", 24] = 1 - on.loc["G1", 24]
    bold.loc["G2", 24] = 1 - bold.loc["G2", 24]
    bold.loc["G1", 3] = 1 - bold.loc["G1", 3]
    ours = pd.concat({"island_1h": on, "changed": bold}, names=["case", "unit"])
    agreement = studies.table2_agreement({"table2": ours, "table2_paper": paper})
    assert agreement == {"equal": 93, "changed_equal": 94, "of": 96}


def test_islanding_cost_grows_with_islanding_hours():
    frame = studies.islanding(make, solve, values=(0, 1, 3, 6))["islanding"]  # a subset: tests stay < 60 s
    assert list(frame.columns) == ["island_hours", *studies.COST_COLUMNS]
    assert frame["island_hours"].tolist() == [0, 1, 3, 6]
    assert_monotone(frame["objective"].tolist(), increasing=True)
    assert (frame["penalty"] == 0).all()  # infinite penalty: the award is a cap, never exceeded


def test_transfer_under_both_readings_of_the_award():
    frames = studies.transfer(make, solve, values=(0.5, 1.4))
    frame, paper = frames["transfer"], frames["transfer_paper"]
    assert list(frame.columns) == ["transfer_scale", "award", *studies.COST_COLUMNS]
    ceiling, take = (frame[frame["award"] == r].set_index("transfer_scale") for r in ("ceiling", "take"))
    assert list(ceiling.index) == list(take.index) == [0.5, 1.4]
    # as a ceiling (c = inf: P_M <= P_sch) a larger award relaxes the problem, so the cost falls
    assert_monotone(ceiling["objective"].tolist(), increasing=False)
    # taking the award adds a floor, so it never costs less (test_model.py checks the floor against brute force)
    assert (take["objective"] >= ceiling["objective"] * (1 - GAP)).all()
    assert paper["factor"].eq(1 / 6).all()  # real convention: the paper's costs are 6x dollars of energy
    assert paper.loc[paper["transfer_scale"] == 1.0, "objective_converted"].item() == pytest.approx(39_566 / 6)


def test_paper_points_and_conversion():
    points = studies.paper_points().set_index("transfer_scale")
    assert points.loc[0.35, "objective"] == 67_552 and points.loc[1.4, "objective"] == 43_304
    assert points.loc[1.0, "objective"] == 39_566 and math.isnan(points.loc[1.0, "generation"])
    assert studies.paper_factor("paper", 6) == 1.0 and studies.paper_factor("paper", 3) == 0.5


def test_dispatch_scenario_is_islanded_in_hours_12_to_14():
    frame = studies.dispatch(make, solve)["dispatch"]
    assert len(frame) == 24
    hour = frame.index.get_level_values("hour")
    islanded = hour.isin([12, 13, 14])
    assert (frame.loc[islanded, "p_m"].abs() < 1e-6).all()
    assert frame["connected"].tolist() == [0.0 if h in (12, 13, 14) else 1.0 for h in hour]
    assert {"G1", "G2", "G3", "G4", "storage", "p_m"} <= set(frame.columns)


def test_penalty_cost_grows_with_the_penalty():
    frame = studies.penalty(make, solve, values=(0, 50, 150, math.inf))["penalty"]  # the full list: CLI test
    assert frame["penalty"].tolist() == [0, 50, 150, math.inf]
    assert "penalty_cost" in frame  # the penalty paid; "penalty" is the rate c
    costs = frame["objective"].to_numpy()
    assert_monotone(costs.tolist(), increasing=True)
    assert (costs[-1] >= costs[:-1] * (1 - GAP)).all()  # c = inf costs at least as much as any finite c
    assert frame["penalty_cost"].iloc[-1] == 0


@pytest.mark.slow
def test_study_command_end_to_end(tmp_path):
    out = tmp_path / "new" / "dir"  # created, parents included
    env = os.environ | {"PYTHONPATH": str(REPO)}
    run = subprocess.run(
        [sys.executable, "-m", "dmosim", "study", "penalty", "--subperiods", "1", "--scenarios", "2",
         "--gap", str(GAP), "--out", str(out)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
    )
    assert run.returncode == 0, run.stderr
    assert (out / "penalty.csv").stat().st_size > 0 and (out / "penalty.png").stat().st_size > 0
    csv = (out / "penalty.csv").read_text().splitlines()
    assert csv[0].startswith("penalty,objective,") and csv[-1].startswith("inf,")
    frame = pd.read_csv(out / "penalty.csv")
    assert frame["penalty"].tolist() == list(studies.PENALTIES)
    assert_monotone(frame["objective"].tolist(), increasing=True)
    assert "[8/8] penalty=inf" in run.stderr and "penalty.png" in run.stdout


def test_out_that_is_a_file_is_a_usage_error(tmp_path, capsys):
    target = tmp_path / "results.txt"
    target.write_text("not a directory")
    assert main(["study", "penalty", "--subperiods", "1", "--scenarios", "2", "--out", str(target)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "not a directory" in err
