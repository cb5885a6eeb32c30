"""Generated fleets (scenarios/diverse.py): drawn per member from its own stream, diverse in what they are drawn for,
each a valid, schedulable case that a fleet file holds exactly."""

from __future__ import annotations

import numpy as np
import pytest

from microgrid_agent.agent.bidding import price_response
from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from scenarios.case import load_case
from scenarios.diverse import LOAD_SHAPES, draw, generate_fleet, schedulable_problems, shaped_loads, summary
from scenarios.fleet import MAX_MEMBERS, load_fleet, member_case, write_fleet


@pytest.fixture(scope="module")
def fleet():
    return generate_fleet(200, seed=1)


@pytest.fixture(scope="module")
def summaries(fleet):
    return [summary(m.drawn) for m in fleet]


def cases(members):
    return [m.drawn for m in members]


def test_a_larger_fleet_extends_a_smaller_one_and_the_seed_decides():
    small, large = generate_fleet(10, seed=7), generate_fleet(50, seed=7)
    assert [m.id for m in large] == [f"mg{i}" for i in range(1, 51)]
    assert cases(large[:10]) == cases(small) and [m.seed for m in large[:10]] == [m.seed for m in small]
    other = generate_fleet(10, seed=8)
    assert all(a != b for a, b in zip(cases(other), cases(small)))
    assert len({m.seed for m in large}) == 50
    assert all(m.case == "paper" and m.scale == 1.0 and m.shift_hours == 0 for m in large)
    assert all(member_case(m) is m.drawn for m in small)  # a drawn member's case is the one drawn


@pytest.mark.parametrize("n", [0, MAX_MEMBERS + 1, True, 2.0])
def test_a_fleet_has_1_to_max_members(n):
    with pytest.raises(ValueError, match="members"):
        generate_fleet(n)


def test_the_drawn_quantities_vary_across_members(summaries):
    col = {k: np.array([s[k] for s in summaries]) for k in ("energy_mwh", "peak_mw", "load_factor",
                                                               "dispatchable_mw", "wind_mw", "solar_mw",
                                                               "storage_mwh", "tie_mw")}
    energy, peak = col["energy_mwh"], col["peak_mw"]
    assert energy.max() / energy.min() > 5  # sizes
    assert np.ptp(col["load_factor"]) > 0.15 and len({s["peak_hour"] for s in summaries}) >= 4  # load shapes
    assert len({s["units"] for s in summaries}) >= 12  # unit mixes of G1..G4
    ratio = col["dispatchable_mw"] / peak
    assert ratio.min() < 0.85 and ratio.max() > 1.05
    renewable = col["wind_mw"] + col["solar_mw"]
    assert (renewable / peak).max() / (renewable / peak).min() > 5
    wind_share = col["wind_mw"] / renewable
    assert (wind_share == 0).sum() > 10 and (wind_share == 1).sum() > 10 and np.std(wind_share) > 0.25
    stored = col["storage_mwh"] / energy
    assert (stored == 0).sum() > 20 and (stored > 0).sum() > 100
    assert stored.max() / stored[stored > 0].min() > 5  # small and large storage
    assert np.ptp(col["tie_mw"] / peak) > 0.4


def test_unit_costs_and_sizes_vary_within_the_base_units_ranges(fleet):
    base = {u.name: u for u in load_case("paper").units}
    for name, unit in base.items():
        drawn = [u for c in cases(fleet) for u in c.units if u.name == name]
        costs = np.array([u.cost for u in drawn])
        assert len(drawn) > 60 and np.ptp(costs) > 0.1 * unit.cost
        assert costs.min() >= 0.9 * unit.cost - 0.01 and costs.max() <= 1.1 * unit.cost + 0.01
        assert all((u.min_up, u.min_down) == (unit.min_up, unit.min_down) for u in drawn)
        ratios = np.array([(u.p_min / u.p_max, u.ramp_up / u.p_max) for u in drawn])
        np.testing.assert_allclose(ratios, [[unit.p_min / unit.p_max, unit.ramp_up / unit.p_max]] * len(drawn),
                                   rtol=1e-3)


def test_load_shapes_keep_the_days_energy_and_move_the_peak():
    base = np.asarray(load_case("paper").fixed_load.forecast)
    u = np.random.default_rng(0).random((400, 22))
    d = draw(u, 4)
    loads = shaped_loads(base, d)
    np.testing.assert_allclose(loads.sum(axis=1), d.size * base.sum(), rtol=1e-9)
    shapes = list(LOAD_SHAPES)
    flat = loads[d.shape == shapes.index("industrial")]
    peaky = loads[d.shape == shapes.index("commercial")]
    assert (flat.max(1) / flat.mean(1)).max() < (peaky.max(1) / peaky.mean(1)).min()
    assert set(np.argmax(loads[d.shape == shapes.index("residential")], axis=1) + 1) <= set(range(19, 24))
    assert set(np.argmax(peaky, axis=1) + 1) <= set(range(12, 17))


def test_every_member_is_a_valid_schedulable_case_that_a_fleet_file_holds_exactly(fleet, tmp_path):
    assert all(not schedulable_problems(m.drawn) for m in fleet)
    path = write_fleet(fleet, tmp_path / "fleet.toml", "a test fleet")
    back = load_fleet(path)  # reads and validates every member's case file
    assert [(m.id, m.seed, m.bus, m.strategy) for m in back] == [(m.id, m.seed, None, None) for m in fleet]
    assert all(m.case == str(tmp_path / "cases" / f"{m.id}.toml") for m in back)
    assert [member_case(m) for m in back] == cases(fleet)
    assert path.read_text().startswith("# a test fleet\n")


def test_a_written_fleet_keeps_what_its_entries_say(tmp_path):
    members = [m for m in load_fleet(_fleet_file(tmp_path))]
    again = load_fleet(write_fleet(members, tmp_path / "again.toml"))
    assert again == members and [member_case(m) for m in again] == [member_case(m) for m in members]


def _fleet_file(tmp_path):
    path = tmp_path / "given.toml"
    path.write_text('[[agents]]\nid = "a"\nscale = 0.5\nshift_hours = -2\nseed = 9\nstrategy = "naive"\nbus = "3"\n\n'
                    '[[agents]]\nid = "b"\ncase = "paper"\n')
    return path


def test_what_makes_a_case_unschedulable_is_named():
    paper = load_case("paper")
    assert schedulable_problems(paper) == []
    weak = paper.model_copy(update={"grid": paper.grid.model_copy(update={"p_m_max": 1.0})})
    assert "demand" in schedulable_problems(weak)[0] and "exceeds units and tie" in schedulable_problems(weak)[0]
    assert any("award" in p for p in schedulable_problems(weak))
    storage = paper.storage.model_copy(update={"c_initial": 0.5})
    assert "storage ES" in schedulable_problems(paper.model_copy(update={"storage": storage}))[0]
    load = paper.loads[0].model_copy(update={"min_up": 5, "d_min": 0.39})
    assert "load L1" in schedulable_problems(paper.model_copy(update={"loads": [load, *paper.loads[1:]]}))[0]


def _pick(fleet, storage: bool, units: set[str]):
    """The first member with (or without) storage whose units are all among ``units``."""
    return next(m.drawn for m in fleet if (m.drawn.storage is not None) == storage
                and {u.name for u in m.drawn.units} <= units)


@pytest.mark.parametrize("storage, units", [(False, {"G1", "G2"}), (True, {"G1", "G2"}), (False, {"G3", "G4"})])
def test_sampled_members_schedule_without_shedding_while_connected_and_bid(fleet, storage, units):
    case = _pick(fleet, storage, units)
    inst = make_instance(case, scenarios=1, sample_size=1, subperiods=1, seed=0)
    schedule = inst.solve(gap=1e-3)
    check_schedule(case, inst.scen, schedule, p_sch=inst.params.p_sch, penalty=inst.params.penalty).raise_if_failed()
    connected = inst.scen.connected.astype(bool)
    assert schedule.dispatch.load_shed[connected].max() < 1e-6
    bid = price_response(case, case.grid.iso_price, subperiods=1, multipliers=(1.0,))  # what its agent bids at
    assert np.abs(bid.quantity).max() <= case.grid.p_m_max + 1e-6 and bid.quantity.max() > 0
