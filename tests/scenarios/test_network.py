"""Feeders as data: the built-ins, the file formats, the rating rule, LinDistFlow's flows and voltages, bad input."""

import json

import numpy as np
import pytest

from scenarios.network import (LOAD_PROFILE, MIN_RATING_MVA, RATING_MARGIN, NetworkError, build, load_network,
                               synthetic)


def _rows(lines=(("0", "1"), ("1", "2"), ("2", "3"), ("1", "4"))):
    buses = [{"name": str(b), "p_mw": 0.0 if b == 0 else 0.1 * b, "q_mvar": 0.0 if b == 0 else 0.05 * b}
             for b in range(5)]
    return buses, [{"from": a, "to": b, "r_ohm": 0.5, "x_ohm": 0.4} for a, b in lines]


def test_feeder5_orientation_and_downstream_by_hand():
    net = load_network("feeder5")
    assert net.substation == "0" and net.n_buses == 5 and net.n_lines == 4
    assert [(net.buses[a], net.buses[b]) for a, b in zip(net.parent, net.child)] == [("0", "1"), ("1", "2"),
                                                                                     ("2", "3"), ("1", "4")]
    # line 0-1 carries every bus's load, 1-2 carries 2 and 3, 2-3 only 3, 1-4 only 4
    assert net.downstream.tolist() == [[0, 1, 1, 1, 1], [0, 0, 1, 1, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 1]]


def test_lines_given_backwards_are_oriented_away_from_the_substation():
    buses, lines = _rows((("1", "0"), ("2", "1"), ("3", "2"), ("4", "1")))
    net = build("t", 12.47, buses, lines, "0")
    assert [(net.buses[a], net.buses[b]) for a, b in zip(net.parent, net.child)] == [("0", "1"), ("1", "2"),
                                                                                     ("2", "3"), ("1", "4")]


def test_lindistflow_matches_a_hand_computed_two_bus_drop():
    net = build("two", 10.0, [{"name": "s"}, {"name": "a", "p_mw": 1.0, "q_mvar": 0.5}],
                [{"from": "s", "to": "a", "r_ohm": 2.0, "x_ohm": 4.0, "s_max_mva": 5}], "s")
    p, q, v = net.lindistflow(net.fixed_p[0], net.fixed_q[0])
    load = LOAD_PROFILE[0]
    assert p.tolist() == pytest.approx([load]) and q.tolist() == pytest.approx([0.5 * load])
    # U_a = 1 - 2 (r P + x Q) / (kV^2 / MVA) = 1 - 2 (2 + 4 x 0.5) load / 100
    assert v[1] == pytest.approx(np.sqrt(1 - 2 * 4 * load / 100)) and v[0] == 1.0


def test_unrated_lines_get_the_rule_and_rated_ones_keep_theirs():
    buses, lines = _rows()
    lines[2]["s_max_mva"] = 7.0
    net = build("t", 12.47, buses, lines, "0")
    peak = max(LOAD_PROFILE)
    s01 = np.hypot(sum(0.1 * b for b in range(1, 5)), sum(0.05 * b for b in range(1, 5))) * peak
    assert net.s_max_mva[0] == pytest.approx(RATING_MARGIN * s01)
    assert net.s_max_mva[2] == 7.0
    assert net.s_max_mva[3] == pytest.approx(max(RATING_MARGIN * np.hypot(0.4, 0.2) * peak, MIN_RATING_MVA))


def test_ieee33_is_baran_and_wu():
    net = load_network("ieee33")
    assert (net.n_buses, net.n_lines, net.base_kv) == (33, 32, 12.66)
    assert net.load_p_mw.sum() == pytest.approx(3.715) and net.load_q_mvar.sum() == pytest.approx(2.3)
    # at nominal load (profile peak 1), LinDistFlow's lowest voltage is bus 17's, a little above AC's 0.9131
    _, _, v = net.lindistflow(net.load_p_mw, net.load_q_mvar)
    assert net.buses[int(v.argmin())] == "17" and 0.9131 < v.min() < 0.92


def test_pandapower_json_and_toml_give_the_same_feeder(tmp_path):
    import pandapower as pp

    net = pp.create_empty_network()
    for b in range(5):
        pp.create_bus(net, vn_kv=12.47, min_vm_pu=0.95, max_vm_pu=1.05)
    pp.create_ext_grid(net, 0)
    for b, (p, q) in {1: (0.4, 0.15), 2: (0.3, 0.1), 3: (0.2, 0.08), 4: (0.25, 0.1)}.items():
        pp.create_load(net, b, p_mw=p, q_mvar=q)
    for a, b, r, x, s in ((0, 1, 0.3, 0.6, 12.0), (1, 2, 0.5, 0.5, 6.0), (2, 3, 0.8, 0.6, 3.0), (1, 4, 0.6, 0.5, 4.0)):
        pp.create_line_from_parameters(net, a, b, length_km=1.0, r_ohm_per_km=r, x_ohm_per_km=x, c_nf_per_km=0,
                                       max_i_ka=s / (np.sqrt(3) * 12.47))
    pp.to_json(net, str(tmp_path / "f.json"))
    a, b = load_network(tmp_path / "f.json"), load_network("feeder5")
    for field in ("parent", "child", "r_ohm", "x_ohm", "s_max_mva", "load_p_mw", "load_q_mvar"):
        assert np.allclose(getattr(a, field), getattr(b, field)), field


def test_synthetic_feeder_is_radial_and_shallow():
    net = synthetic(1000)
    assert net.n_lines == 999 and net.downstream.sum(axis=0).max() < 60
    assert synthetic(1000).r_ohm.tolist() == net.r_ohm.tolist()  # seeded


@pytest.mark.parametrize("change, message", [
    (lambda b, l: l.append({"from": "3", "to": "4", "r_ohm": 1, "x_ohm": 1}), "meshed"),
    (lambda b, l: l.pop(), "not connected"),
    (lambda b, l: l.__setitem__(3, {"from": "2", "to": "3", "r_ohm": 1, "x_ohm": 1}), "radial"),
    (lambda b, l: l[1].update(r_ohm=0.0, x_ohm=0.0), r"needs r \+ x >= 1e-06 ohm"),
    (lambda b, l: l[1].update(to="9"), "no bus '9'"),
    (lambda b, l: l[1].update(to="1"), "to itself"),
    (lambda b, l: b[0].update(p_mw=1.0), "substation bus 0 carries no fixed load"),
    (lambda b, l: b[2].update(v_min=1.1), "are not limits"),
    (lambda b, l: b.append({"name": "2"}), "listed twice"),
    (lambda b, l: l[0].update(s_max_mva=-1), "must be > 0"),
    (lambda b, l: l[0].update(r_ohm=float("nan")), "finite number"),
    # what the DMO's clearing and messages cannot carry (docs/network.md, "Limits")
    (lambda b, l: b[4].update(name="x" * 65), r"bus 5's name 'x{64}'... \(65 characters\): a name is 1..64"),
    (lambda b, l: b[4].update(name="a\nb"), r"bus 5's name 'a\\nb' \(3 characters\): a name is 1..64 printable"),
    (lambda b, l: b[4].update(name=""), "bus 5's name '' \\(0 characters\\)"),
    (lambda b, l: b[4].update(name=True), "bus 5's name True: a name"),
    (lambda b, l: b[3].update(p_mw=1e308), r"bus 3 p_mw must be >= -10,000 and <= 10,000, got 1e\+308"),
    (lambda b, l: b[3].update(p_mw=0.001, q_mvar=0.5), r"bus 3: .* \|q_mvar\| is at most 10 x p_mw"),
    (lambda b, l: l[0].update(x_ohm=1e5), r"x_ohm must be >= 0 and <= 10,000, got 100000"),
    (lambda b, l: l[0].update(s_max_mva=1e7), r"s_max_mva must be > 0 and <= 1e\+06"),
])
def test_bad_feeders_are_refused_in_one_line(change, message):
    buses, lines = _rows()
    change(buses, lines)
    with pytest.raises(NetworkError, match=message) as err:
        build("t", 12.47, buses, lines, "0")
    assert "\n" not in str(err.value)


def test_bad_network_files_name_the_file_and_field(tmp_path):
    f = tmp_path / "n.toml"
    f.write_text('base_kv = 12.47\nsubstation = "0"\nbogus = 1\n[[buses]]\nname = "0"\n')
    with pytest.raises(NetworkError, match=r"n.toml: network n: unknown field 'bogus'"):
        load_network(f)
    f.write_text('base_kv = 12.47\nsubstation = "0"\n[[buses]]\nname = "0"\np = 1\n[[lines]]\n')
    with pytest.raises(NetworkError, match=r"buses\[0\].p: unknown field"):
        load_network(f)
    (tmp_path / "x.json").write_text(json.dumps({"not": "pandapower"}))
    with pytest.raises(NetworkError, match="x.json: not a pandapower JSON"):
        load_network(tmp_path / "x.json")
    with pytest.raises(NetworkError, match="unknown network 'ieee34'"):
        load_network("ieee34")


def test_bus_of_refuses_missing_buses_and_the_substation():
    net = load_network("feeder5")
    assert net.bus_of("3") == 3 and net.bus_of(3) == 3
    with pytest.raises(NetworkError, match="no bus '7' in network feeder5"):
        net.bus_of("7")
    with pytest.raises(NetworkError, match="substation"):
        net.bus_of("0")


@pytest.mark.parametrize("options, message", [
    ({"base_kv": 0.05}, "base_kv must be >= 0.1 and <= 1,000, got 0.05"),
    ({"power_factor": 0.4}, "power_factor must be >= 0.5 and <= 1, got 0.4"),
    ({"load_scale": 11.0}, "load_scale must be > 0 and <= 10, got 11"),
    ({"rating_margin": 0.0}, "rating_margin must be > 0 and <= 10, got 0"),
    ({"load_profile": (1.0,) * 23 + (1e308,)}, r"load_profile hour 24 must be >= 0 and <= 10, got 1e\+308"),
    ({"name": "n" * 65}, r"the network's name 'n{64}'... \(65 characters\)"),
])
def test_options_beyond_their_limits_are_refused_in_one_line(options, message):
    buses, lines = _rows()
    settings = {"name": "t", "base_kv": 12.47, **options}
    with pytest.raises(NetworkError, match=message) as err:
        build(settings.pop("name"), settings.pop("base_kv"), buses, lines, "0", **settings)
    assert "\n" not in str(err.value)


def test_names_of_64_characters_and_loads_at_the_limits_load():
    buses, lines = _rows()
    buses[4]["name"] = lines[3]["to"] = "x" * 64
    buses[3].update(p_mw=10_000.0, q_mvar=-10_000.0)
    net = build("n" * 64, 1_000.0, buses, lines, "0", power_factor=0.5, load_scale=10.0)
    assert net.name == "n" * 64 and net.buses[4] == "x" * 64 and net.fixed_p.max() == 10_000.0 * 10.0
