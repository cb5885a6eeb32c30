"""Fleets of microgrids: derived cases, seeded fleets and fleet files with one-line errors."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from scenarios.generation import forecast_scenario
from microgrid_agent.checker import check_schedule
from microgrid_agent.model import Params
from microgrid_agent.solvers.extensive import solve
from scenarios.case import DATA_DIR, CaseError, load_case
from scenarios.fleet import FleetError, FleetMember, derive_case, load_fleet, make_fleet, member_case


@pytest.fixture(scope="module")
def base():
    return load_case("paper")


def test_scale_one_shift_zero_is_the_base(base):
    assert derive_case(base, 1.0, 0, base.name) == base
    renamed = derive_case(base, 1, 0, "other")
    assert renamed.name == "other" and renamed.model_dump(exclude={"case"}) == base.model_dump(exclude={"case"})


def test_scaled_case_scales_every_power_and_energy(base):
    s = 1.3
    c = derive_case(base, s, 0, "big")
    for field in ("p_min", "p_max", "ramp_up", "ramp_down"):
        np.testing.assert_allclose(c.unit_array(field), s * base.unit_array(field))
    for field in ("cost", "startup_cost", "min_up", "min_down"):
        np.testing.assert_array_equal(c.unit_array(field), base.unit_array(field))
    for field in ("d_min", "d_max", "energy"):
        np.testing.assert_allclose(c.load_array(field), s * base.load_array(field))
    np.testing.assert_array_equal(c.load_windows, base.load_windows)
    for field in ("c_max", "p_dch_min", "p_dch_max", "p_ch_min", "p_ch_max", "c_initial"):
        assert getattr(c.storage, field) == pytest.approx(s * getattr(base.storage, field))
    assert c.storage.min_charge == base.storage.min_charge
    for mine, theirs in zip(c.renewables, base.renewables):
        assert mine.capacity == pytest.approx(s * theirs.capacity)
        np.testing.assert_allclose(mine.forecast, s * np.asarray(theirs.forecast))
    np.testing.assert_allclose(c.fixed_load.forecast, s * np.asarray(base.fixed_load.forecast))
    np.testing.assert_allclose(c.grid.p_sch, s * np.asarray(base.grid.p_sch))
    assert c.grid.p_m_max == pytest.approx(s * base.grid.p_m_max)
    assert (c.grid.penalty, c.grid.voll, c.grid.iso_price) == (base.grid.penalty, base.grid.voll, base.grid.iso_price)
    assert c.uncertainty == base.uncertainty
    assert "derived" in c.case.provenance


def test_shift_rolls_profiles_but_not_windows_or_prices(base):
    c = derive_case(base, 1.0, -2, "early")
    np.testing.assert_allclose(c.fixed_load.forecast, np.roll(base.fixed_load.forecast, -2))
    np.testing.assert_allclose(c.renewables[1].forecast, np.roll(base.renewables[1].forecast, -2))
    np.testing.assert_allclose(c.grid.p_sch, np.roll(base.grid.p_sch, -2))
    assert c.grid.iso_price == base.grid.iso_price and c.loads == base.loads


def test_derived_case_schedules_and_verifies(base):
    c = derive_case(base, 0.7, 1, "small")
    scen = forecast_scenario(c, 1)
    params = Params(np.asarray(c.grid.p_sch), c.grid.penalty)
    schedule = solve(c, scen, params, gap=1e-3)
    check_schedule(c, scen, schedule, p_sch=params.p_sch, penalty=params.penalty).raise_if_failed()


@pytest.mark.parametrize("scale", [0.0, -1.0, float("inf"), float("nan")])
def test_bad_scale_is_a_case_error(base, scale):
    with pytest.raises(CaseError, match="scale"):
        derive_case(base, scale, 0, "bad")


def test_fleet_is_reproducible_per_seed(base):
    fleet = make_fleet(6, seed=4)
    assert fleet == make_fleet(6, seed=4)
    assert fleet != make_fleet(6, seed=5)
    assert make_fleet(3, seed=4) == fleet[:3]
    assert [m.id for m in fleet] == [f"mg{i}" for i in range(1, 7)]
    assert (fleet[0].scale, fleet[0].shift_hours) == (1.0, 0) and member_case(fleet[0]) == base
    assert all(0.6 <= m.scale <= 1.4 and -2 <= m.shift_hours <= 2 for m in fleet)
    assert len({m.seed for m in fleet}) == 6
    for m in fleet[1:]:
        c = member_case(m)
        assert c.name == f"paper-{m.id}"
        assert c.grid.p_m_max == pytest.approx(m.scale * base.grid.p_m_max)


def write(tmp_path, text, name="fleet.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_fleet_file_reads_members_and_relative_cases(tmp_path, base):
    (tmp_path / "cases").mkdir()
    shutil.copy(DATA_DIR / "paper.toml", tmp_path / "cases" / "mine.toml")
    path = write(tmp_path, """
[[agents]]
id = "mg1"
case = "paper"
scale = 1.0
shift_hours = 0
seed = 1

[[agents]]
id = "north_2"
case = "cases/mine.toml"
scale = 0.8
shift_hours = -1
""")
    fleet = load_fleet(path)
    assert fleet[0] == FleetMember("mg1", "paper", 1.0, 0, 1)
    assert fleet[1].case == str(tmp_path / "cases" / "mine.toml") and fleet[1].seed == 2
    assert member_case(fleet[0]) == base
    assert member_case(fleet[1]).grid.p_m_max == pytest.approx(0.8 * base.grid.p_m_max)


AGENT = '[[agents]]\nid = "mg1"\n'


@pytest.mark.parametrize("text, where", [
    ('[[agents]]\ncase = "paper"\n', "agents[0].id"),
    (AGENT + AGENT, "agents[1].id"),
    ('[[agents]]\nid = "9lives"\n', "agents[0].id"),
    ('[[agents]]\nid = "dmo"\n', "agents[0].id"),
    ('[[agents]]\nid = "recorder"\n', "agents[0].id"),
    (AGENT + "scale = 0\n", "agents[mg1].scale"),
    (AGENT + "scale = -1.5\n", "agents[mg1].scale"),
    (AGENT + 'scale = "big"\n', "agents[mg1].scale"),
    (AGENT + 'case = "nowhere"\n', "agents[mg1].case"),
    (AGENT + "shift_hours = 30\n", "agents[mg1].shift_hours"),
    (AGENT + "seed = -1\n", "agents[mg1].seed"),
    (AGENT + "colour = 1\n", "agents[0].colour"),
    ("title = 'x'\n", "title"),
    ("", "agents"),
])
def test_bad_fleet_file_names_file_and_field(tmp_path, text, where):
    path = write(tmp_path, text)
    with pytest.raises(FleetError) as err:
        load_fleet(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {where}: ") and "\n" not in message


def test_bad_case_file_in_fleet_is_a_fleet_error(tmp_path):
    write(tmp_path, "[case]\nname = 'x'\n", "broken.toml")
    path = write(tmp_path, AGENT + 'case = "broken.toml"\n')
    with pytest.raises(FleetError, match=r"agents\[mg1\]\.case: .*broken\.toml"):
        load_fleet(path)


def test_unreadable_fleet_files(tmp_path):
    with pytest.raises(FleetError, match="not found"):
        load_fleet(tmp_path / "missing.toml")
    with pytest.raises(FleetError, match="not valid TOML"):
        load_fleet(write(tmp_path, "[[agents]\n"))
