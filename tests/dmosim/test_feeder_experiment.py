"""A feeder in an experiment: the [network] section, each agent's bus (fleet, list or spread), and the bus rule of
registration."""

import pytest

from dmo.market.acceptance import check_bus
from dmosim.experiment.spec import ExperimentError, load_experiment, parse_experiment
from dmosim.launch.roles import bus_of, fleet_of, network_of, placement_of, resolved
from messages import Registration
from scenarios.network import load_network


def _experiment(**network):
    return parse_experiment({"agents": {"count": 4}, "network": network})


def test_agents_are_spread_over_the_feeder_unless_placed():
    e = _experiment(feeder="feeder5")
    net = network_of(e)
    assert placement_of(e, net) == {"mg1": "1", "mg2": "2", "mg3": "3", "mg4": "4"}
    e = _experiment(feeder="ieee33", buses=["17", "32"])
    placed = placement_of(e, network_of(e))  # the rest spread: agent i of 4 at bus 1 + i x 32 / 4 of the feeder's
    assert placed == {"mg1": "17", "mg2": "32", "mg3": "17", "mg4": "25"}


def test_a_fleet_entrys_bus_wins_and_the_run_writes_every_bus_down(tmp_path):
    (tmp_path / "fleet.toml").write_text('[[agents]]\nid = "a"\nbus = 3\n\n[[agents]]\nid = "b"\n')
    (tmp_path / "e.toml").write_text('[agents]\nfleet = "fleet.toml"\n[network]\nfeeder = "feeder5"\nbuses = ["1", "4"]\n')
    e = resolved(load_experiment(tmp_path / "e.toml"))
    assert e.network.buses == ["3", "4"]
    assert [bus_of(e, m) for m in fleet_of(e)] == ["3", "4"]


def test_a_network_file_is_taken_relative_to_the_experiment(tmp_path):
    from scenarios.case import DATA_DIR

    (tmp_path / "f.toml").write_text((DATA_DIR / "feeder5.toml").read_text())
    (tmp_path / "e.toml").write_text('[network]\nfeeder = "f.toml"\nload_scale = 2.0\n')
    e = resolved(load_experiment(tmp_path / "e.toml"))
    assert e.network.feeder == str(tmp_path / "f.toml")
    assert network_of(e).fixed_p.sum() == pytest.approx(2 * load_network("feeder5").fixed_p.sum())


@pytest.mark.parametrize("network, message", [
    ({"feeder": "feeder5", "buses": ["9"]}, "no bus '9' in network feeder5"),
    ({"feeder": "feeder5", "buses": ["0"]}, "substation"),
    ({"feeder": "feeder5", "buses": ["1"] * 5}, "5 buses for 4 agents"),
    ({"feeder": "nowhere"}, "unknown network 'nowhere'"),
    ({"feeder": "feeder5", "voltage_margin": 0.06}, "bus 1 has none left"),
    ({"buses": ["1"]}, "network.feeder names none"),
])
def test_bad_placements_are_one_line(network, message):
    e = _experiment(**network)
    with pytest.raises(ExperimentError, match=message) as err:
        placement_of(e, network_of(e))
    assert "\n" not in str(err.value)


def test_a_feeder_no_clearing_can_serve_is_refused_before_the_run(tmp_path):
    (tmp_path / "high.toml").write_text('base_kv = 10.0\nsubstation = "0"\n[[buses]]\nname = "0"\n[[buses]]\n'
                                        'name = "1"\np_mw = 1.0\nv_min = 1.01\n[[lines]]\nfrom = "0"\nto = "1"\n'
                                        'r_ohm = 0.1\nx_ohm = 0.1\n')
    e = _experiment(feeder=str(tmp_path / "high.toml"))
    with pytest.raises(ExperimentError, match="network.feeder: network high: the hour cannot clear even with every "
                                              "fixed load shed"):
        network_of(e)


def test_a_feeder_needs_bids():
    with pytest.raises(ExperimentError, match="a feeder is cleared from bids"):
        parse_experiment({"market": {"mode": "fixed"}, "network": {"feeder": "feeder5"}})


def _registration(bus):
    return Registration(sender="mg1", market_day="2026-07-01", case="paper", max_import_mw=1.0, max_export_mw=1.0,
                        bus=bus)


def test_registration_bus_rule():
    net = load_network("feeder5")
    assert check_bus(_registration(None), None, {}) is None
    assert check_bus(_registration("1"), None, {})[0] == "invalid"  # a bus, and no feeder
    assert check_bus(_registration(None), net, {"mg1": "2"}) is None  # the run's placement
    assert check_bus(_registration("2"), net, {"mg1": "2"}) is None
    assert "placed it at bus 2" in check_bus(_registration("3"), net, {"mg1": "2"})[1]
    assert check_bus(_registration("3"), net, {}) is None  # an agent the run does not place names its own
    assert "names no bus" in check_bus(_registration(None), net, {})[1]
    assert "substation" in check_bus(_registration("0"), net, {})[1]
    assert "no bus '7'" in check_bus(_registration("7"), net, {})[1]


def test_the_feeder_example_checks(capsys):
    from pathlib import Path

    from dmosim.cli.main import main

    example = Path(__file__).resolve().parents[2] / "examples" / "feeder.toml"
    assert main(["run", str(example), "--check"]) == 0
    out = capsys.readouterr().out
    assert "10 agents" in out and "on feeder ieee33 at buses 1, 2, 18, 13, 14, 16, 17, 29, 30, 32" in out


def test_a_feeder_clears_on_the_ac_flow_unless_the_experiment_or_a_flag_says_lindistflow(cli, tmp_path):
    from dmosim.launch.roles import day_config

    assert day_config(_experiment(feeder="feeder5")).clearing == "ac"
    assert day_config(_experiment(feeder="feeder5", clearing="lindistflow")).clearing == "lindistflow"
    with pytest.raises(ExperimentError, match="network.clearing") as err:
        _experiment(feeder="feeder5", clearing="acopf")
    assert "\n" not in str(err.value)
    out = cli("run", "--feeder", "feeder5", "--clearing", "acopf", "--out", str(tmp_path / "run"))
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "--clearing" in out.stderr, out.stderr
    assert not (tmp_path / "run").exists()


def test_the_spill_price_reaches_the_dmo_and_a_bad_one_is_one_line(cli, tmp_path):
    from dmosim.launch.roles import day_config

    assert day_config(_experiment(feeder="feeder5")).spill_price == 0.0
    assert day_config(_experiment(feeder="feeder5", spill_price=25.0)).spill_price == 25.0
    with pytest.raises(ExperimentError, match="network.spill_price") as err:
        _experiment(feeder="feeder5", spill_price=-1.0)
    assert "\n" not in str(err.value)
    out = cli("run", "--feeder", "feeder5", "--spill-price", "-5", "--out", str(tmp_path / "run"))
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "--spill-price" in out.stderr, out.stderr
