"""The decomposition in one branch-and-bound tree (microgrid_agent/solvers/tree.py, SCIP through PySCIPOpt): it
agrees with the extensive form and with Benders within the gap, its schedules pass the checker, and without
PySCIPOpt installed the method is refused in one line before anything is solved."""

from __future__ import annotations

import importlib.util

import pytest

from dmosim.cli import main
from dmosim.experiment.spec import ScheduleSettings
from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from microgrid_agent.solvers import routes
from scenarios.case import load_case

GAP = 0.005


@pytest.fixture(scope="module")
def small():
    return make_instance(load_case("paper"), scenarios=3, sample_size=3, subperiods=2, seed=2, island_hours=1)


@pytest.mark.slow
def test_the_tree_agrees_with_the_extensive_form_and_benders_within_the_gap(small):
    pytest.importorskip("pyscipopt")
    reference = small.solve(gap=1e-6)
    tree = small.solve(method="tree", gap=GAP, workers=2)
    benders = small.solve(method="benders", gap=GAP, workers=2)
    check_schedule(small.case, small.scen, tree).raise_if_failed()
    assert tree.extra["method"] == "tree" and tree.status == "optimal"
    assert tree.bound <= reference.objective * (1 + 1e-6) and tree.objective >= reference.bound * (1 - 1e-6)
    assert tree.mip_gap <= GAP + 1e-9
    assert tree.objective <= benders.bound / (1 - GAP) + 1e-6 and benders.objective <= tree.bound / (1 - GAP) + 1e-6
    shares = tree.extra["decomposition"]
    assert shares["iterations"] == shares["lp_iterations"] + 1  # the LP phase's masters, then the one tree


def test_without_pyscipopt_the_tree_method_is_refused_in_one_line(monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyscipopt" else real(name, *a))
    assert main(["solve", "--method", "tree", "--scenarios", "2", "--subperiods", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install 'dmosim[scip]'" in err and "--method" in err
    with pytest.raises(ValueError, match="PySCIPOpt"):
        ScheduleSettings(method="tree")
    assert routes.check_available("benders") == "benders"  # the other routes need nothing more
