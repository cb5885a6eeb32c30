"""The AC check of a feeder's hours: a hand-solved two-bus line, the built-in feeders' published base cases (and a
day cleared on the largest), the figures against pandapower run independently, the violations, an hour with no AC
solution, bad input, and a quiet stdout/stderr."""

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmo.market.acflow import NOT_CONVERGED, check_hours
from scenarios.network import LOAD_PROFILE, build, load_network

ROOT = Path(__file__).resolve().parents[2]
PEAK = LOAD_PROFILE.index(1.0)  # the hour the fixed load is at its nominal value


def test_two_bus_line_solves_the_quadratic():
    # 10 kV, z_base = 100 ohm: r = 0.02, x = 0.04 p.u.; the substation held at 1.02 p.u.
    net = build("two", 10.0, [{"name": "s"}, {"name": "a", "p_mw": 1.0, "q_mvar": 0.5}],
                [{"from": "s", "to": "a", "r_ohm": 2.0, "x_ohm": 4.0, "s_max_mva": 5.0}], "s", power_factor=0.8)
    net = dataclasses.replace(net, v_substation=1.02)
    (check,) = check_hours(net, [[0.0, 0.6]], hours=[PEAK])
    p, q = 1.0 + 0.6, 0.5 + 0.6 * 0.75  # the microgrid's Q at power factor 0.8 is 0.75 P
    r, x, vs = 0.02, 0.04, 1.02
    # |V_s|^2 |V|^2 = |V|^4 + 2 (rP + xQ) |V|^2 + |z|^2 |S|^2: a quadratic in |V|^2
    b = vs ** 2 - 2 * (r * p + x * q)
    v = math.sqrt((b + math.sqrt(b ** 2 - 4 * (r ** 2 + x ** 2) * (p ** 2 + q ** 2))) / 2)
    losses = r * (p ** 2 + q ** 2) / v ** 2
    assert check.converged and v < 0.95 and check.violations == (f"undervoltage a {v:.4f}<0.95",)
    assert check.v_pu == pytest.approx((vs, v), abs=1e-6) and check.v_min_bus == "a"
    assert check.losses_mw == pytest.approx(losses, abs=1e-6)
    assert check.substation_mw == pytest.approx(p + losses, abs=1e-6)
    # LinDistFlow drops the losses: its flow is the load, its voltage sqrt(b)
    assert check.flow_error_mw == pytest.approx(losses, abs=1e-6)
    assert check.voltage_error_pu == pytest.approx(math.sqrt(b) - v, abs=1e-6)
    sending = math.hypot(p + losses, q + x * (p ** 2 + q ** 2) / v ** 2)
    assert check.max_loading == pytest.approx(sending / 5.0, abs=1e-6) and check.max_loading_line == "s-a"


def test_ieee33_base_case_is_baran_and_wus():
    # Baran and Wu (1989) publish 0.9131 p.u. at their bus 18 (pandapower's and our bus 17) and 202.7 kW of
    # losses at nominal load: to the digits printed, so within half the last one
    (check,) = check_hours(load_network("ieee33"), np.zeros((1, 33)), hours=[PEAK])
    assert check.v_min_bus == "17" and check.v_min_pu == pytest.approx(0.9131, abs=5e-5)
    assert check.losses_mw == pytest.approx(0.2027, abs=5e-5)
    assert check.v_max_bus == "0" and check.v_max_pu == 1.0


def test_ieee69_base_case_is_baran_and_wus():
    # the 69-bus feeder's published base case: 3.8021 MW and 2.6947 Mvar of load, the lowest voltage 0.9092 p.u. at
    # bus 65 and 225.0 kW of losses (to the digits printed), by pandapower and by the branch flow alike
    from dmo.market.branchflow import BranchFlow

    net = load_network("ieee69")
    (check,) = check_hours(net, np.zeros((1, 69)), hours=[PEAK])
    assert net.fixed_p[PEAK].sum() == pytest.approx(3.8021) and net.fixed_q[PEAK].sum() == pytest.approx(2.6947)
    assert check.v_min_bus == "65" and check.v_min_pu == pytest.approx(0.9092, abs=5e-5)
    assert check.losses_mw == pytest.approx(0.2250, abs=5e-5) and check.violations == ()
    point = BranchFlow(net).solve(net.fixed_p[PEAK], net.fixed_q[PEAK])
    assert point.v.min() == pytest.approx(check.v_min_pu, abs=1e-9) and point.losses == pytest.approx(check.losses_mw)


def test_mantovani136_base_case_is_the_published_one():
    # the 136-bus feeder's published base case: 18.3138 MW and 7.9326 Mvar of load, the lowest voltage 0.9307 p.u.
    # at bus 117 and 320.36 kW of losses (to the digits printed), by pandapower and by the branch flow alike. Bus
    # 118, an unloaded end behind bus 117, is at the same voltage to the bit: the lowest is the first in bus order
    from dmo.market.branchflow import BranchFlow

    net = load_network("mantovani136")
    (check,) = check_hours(net, np.zeros((1, 136)), hours=[PEAK])
    assert net.fixed_p[PEAK].sum() == pytest.approx(18.3138, abs=5e-5)
    assert net.fixed_q[PEAK].sum() == pytest.approx(7.9326, abs=5e-5)
    assert check.v_min_bus == "117" and check.v_min_pu == pytest.approx(0.9307, abs=5e-5)
    assert check.losses_mw == pytest.approx(0.32036, abs=5e-6) and check.violations == ()
    point = BranchFlow(net).solve(net.fixed_p[PEAK], net.fixed_q[PEAK])
    assert net.buses[int(np.argmin(point.v))] == "117"
    assert point.v.min() == pytest.approx(check.v_min_pu, abs=1e-9) and point.losses == pytest.approx(check.losses_mw)


def test_a_day_on_mantovani136_clears_on_the_ac_flow_within_every_limit():
    # a buyer at the far bus 117 and a seller near the substation, every hour: the day clears on the AC flow with
    # no hour's plan breaking a limit in it and no load shed; a line on bus 117's path (109-110 or 108-109, rated by
    # the rule) holds the buyer below its 1 MW, so its price is its bid, and the seller's bus price is the energy
    # price and the losses its sale saves
    from dmo.market.clearing import BidCurve, Step
    from dmo.market.distflow import clear_network

    def every_hour(agent, price, mw):
        return BidCurve(agent, ((Step(price, mw),),) * 24)

    net = load_network("mantovani136")
    r = clear_network([every_hour("far", 90.0, 1.0), every_hour("near", 30.0, -0.5)], net,
                      {"far": "117", "near": "2"}, 40.0, 1e6, 1e6, method="ac")
    assert r.ac_voltage_excess_pu == (0.0,) * 24 and r.ac_overload == (0.0,) * 24 and r.shed_mw.sum() == 0.0
    assert all(0.0 < mw < 1.0 for mw in r.awards["far"]) and r.awards["near"] == (-0.5,) * 24
    assert r.agent_price["far"] == (90.0,) * 24 and r.congested == ("line",) * 24
    path = set(np.flatnonzero(net.downstream[:, net.index["117"]]).tolist())  # the lines from the substation to 117
    assert all(lines and set(lines) <= path for lines in r.lines_binding)
    assert all(p > 40.0 for p in r.agent_price["near"]) and r.price == (40.0,) * 24


def _independent_ac(hours, p_mw):
    """pandapower's own case33bw, its loads scaled to each hour and the microgrids added as loads, each hour
    from a flat start: per hour the bus voltages, each line's (P, S) at the end power enters, losses, import."""
    import pandapower as pp
    import pandapower.networks as pn

    out = []
    for hour, p in zip(hours, p_mw):
        case = pn.case33bw()
        case.load["scaling"] = LOAD_PROFILE[hour]
        for bus in np.flatnonzero(p):
            pp.create_load(case, bus, p_mw=p[bus], q_mvar=0.0)
        pp.runpp(case, numba=False, init="flat")
        live = case.line[case.line.in_service]
        res = case.res_line.loc[live.index]
        out.append({"v": case.res_bus.vm_pu.to_numpy(), "from": live.from_bus.to_numpy(), "res": res,
                    "losses": res.pl_mw.sum(), "import": case.res_ext_grid.p_mw.iat[0]})
    return out


def test_figures_match_pandapower_run_alone_and_lindistflow_is_above_ac():
    net = load_network("ieee33")
    hours = [0, 7, PEAK, PEAK, 23]
    p = np.zeros((len(hours), 33))
    p[1:, [17, 32]] = [[0.1, 0.0], [0.2, 0.15], [-0.3, 0.4], [0.05, -0.2]]  # imports and exports, on two laterals
    checks = check_hours(net, p, hours=hours, margin=0.01)
    _, _, ldf_v = net.lindistflow(net.fixed_p[hours] + p, net.fixed_q[hours])
    ldf_p = (net.fixed_p[hours] + p) @ net.downstream.T
    backwards = 0
    for k, (check, ac) in enumerate(zip(checks, _independent_ac(hours, p))):
        assert check.hour == hours[k] and check.converged and check.margin == 0.01
        assert np.allclose(check.v_pu, ac["v"], atol=1e-7)
        forward = ac["from"] == net.parent  # case33bw's lines, in order, some given from the far end
        res = ac["res"]
        p_near = np.where(forward, res.p_from_mw, res.p_to_mw)
        p_from, q_from, p_to, q_to = (np.where(forward, res[a], res[b]) for a, b in (
            ("p_from_mw", "p_to_mw"), ("q_from_mvar", "q_to_mvar"), ("p_to_mw", "p_from_mw"),
            ("q_to_mvar", "q_from_mvar")))
        sending = np.where(p_from >= 0, np.hypot(p_from, q_from), np.hypot(p_to, q_to))
        backwards += (p_from < 0).sum()
        assert np.allclose(check.loading, sending / net.s_max_mva, atol=1e-7)
        assert check.max_loading == pytest.approx(max(sending / net.s_max_mva), abs=1e-7)
        assert check.voltage_error_pu == pytest.approx(np.abs(ldf_v[k] - ac["v"]).max(), abs=1e-7)
        assert check.flow_error_mw == pytest.approx(np.abs(ldf_p[k] - p_near).max(), abs=1e-7)
        assert check.losses_mw == pytest.approx(ac["losses"], abs=1e-7)
        assert check.substation_mw == pytest.approx(ac["import"], abs=1e-7)
        assert check.v_min_pu == pytest.approx(ac["v"].min(), abs=1e-7)
        assert check.v_min_bus == net.buses[int(ac["v"].argmin())]
        # LinDistFlow neglects the losses: it carries less and so sees every voltage higher
        assert (ldf_v[k] >= ac["v"] - 1e-9).all() and check.voltage_error_pu > 0
    assert backwards > 0  # the exports make some flows run back, sent from the line's far end


def test_violations_name_each_broken_limit_and_a_quiet_hour_has_none():
    net = load_network("feeder5")
    p = np.zeros((3, 5))
    p[1, 3] = 4.0  # 4 MW more at the far end: line 2-3 (3 MVA) overloads and bus 3 sags below 0.95
    p[2, 4] = -3.0  # 3 MW out at bus 4 with the substation at 1.04 p.u.: bus 4 rises above 1.05
    quiet, far = check_hours(net, p[:2], hours=[PEAK, PEAK], margin=0.02)
    assert quiet.violations == () and quiet.margin == 0.02
    l23 = net.line_to[3]
    assert far.violations == (f"undervoltage 3 {far.v_pu[3]:.4f}<0.95", f"overload 2-3 {100 * far.loading[l23]:.1f}%")
    assert far.v_pu[3] < 0.95 and far.loading[l23] > 1 and far.max_loading_line == "2-3"
    assert all(v >= 0.95 for b, v in enumerate(far.v_pu) if b != 3)
    assert sum(x > 1 for x in far.loading) == 1
    (high,) = check_hours(dataclasses.replace(net, v_substation=1.04), p[2:], hours=[3])
    assert high.violations == (f"overvoltage 4 {high.v_pu[4]:.4f}>1.05",) and high.v_max_bus == "4"


def test_an_hour_with_no_ac_solution_is_reported_and_the_next_is_solved_afresh():
    net = load_network("feeder5")
    p = np.zeros((3, 5))
    p[1, 3] = 1e4  # 10 GW at 12.47 kV: no voltage carries it
    checks = check_hours(net, p, hours=[5, 6, 7])
    assert [c.converged for c in checks] == [True, False, True]
    assert checks[1].violations == (NOT_CONVERGED,) and math.isnan(checks[1].v_min_pu)
    row = checks[1].as_dict()
    assert row["converged"] is False and row["v_min_pu"] is None and row["violations"] == [NOT_CONVERGED]
    json.dumps(row, allow_nan=False)
    json.dumps(checks[1].profile(), allow_nan=False)
    (alone,) = check_hours(net, p[2:], hours=[7])
    assert checks[2].v_pu == pytest.approx(alone.v_pu, abs=1e-9)


def test_as_dict_is_json_ready_without_the_profiles():
    net = load_network("feeder5")
    check = check_hours(net, np.zeros((24, 5)))[PEAK]
    row = json.loads(json.dumps(check.as_dict(), allow_nan=False))
    assert "v_pu" not in row and "loading" not in row
    assert row["v_min_pu"] == round(check.v_min_pu, 6) and row["max_loading"] == round(check.max_loading, 4)
    profile = check.profile()
    assert profile["hour"] == PEAK and len(profile["v_pu"]) == 5 and len(profile["loading"]) == 4


@pytest.mark.parametrize("call, message", [
    (lambda net: check_hours(net, np.zeros((24, 4))), r"hours x buses \(H >= 1 x 5\)"),
    (lambda net: check_hours(net, np.zeros((25, 5))), "give ``hours``"),
    (lambda net: check_hours(net, np.zeros((2, 5)), hours=[3, 24]), "one hour index 0..23 per row"),
    (lambda net: check_hours(net, np.zeros((2, 5)), hours=[3]), "one hour index 0..23 per row"),
    (lambda net: check_hours(net, np.zeros((2, 5)), q_mvar=np.zeros((1, 5))), r"q_mvar must be hours x buses"),
    (lambda net: check_hours(net, np.full((1, 5), np.nan)), "p_mw must be finite"),
    (lambda net: check_hours(net, np.eye(1, 5)), "substation bus 0 carries no microgrid"),
    (lambda net: check_hours(net, np.zeros((1, 5)), margin=-0.01), "margin must be"),
])
def test_bad_input_is_refused_in_one_line(call, message):
    with pytest.raises(ValueError, match=message) as err:
        call(load_network("feeder5"))
    assert "\n" not in str(err.value)


@pytest.mark.slow  # what importing pandapower says shows only in a fresh interpreter
@pytest.mark.parametrize("first", ["feeder5", "ieee33"])
def test_nothing_reaches_stdout_or_stderr_from_the_first_check(first):
    # A fresh interpreter logging at INFO like a dmosim role, every warning shown. pandapower is imported first by
    # the check (feeder5 is plain TOML) or by the feeder (ieee33 is pandapower's case33bw): quiet either way.
    code = ("import logging, numpy as np; logging.basicConfig(level=logging.INFO)\n"
            "from scenarios.network import load_network\n"
            "from dmo.market.acflow import check_hours\n"
            f"net = load_network({first!r})\n"
            "p = np.zeros((2, net.n_buses)); p[1, 3] = 1e4\n"
            "assert [c.converged for c in check_hours(net, p)] == [True, False]\n")
    out = subprocess.run([sys.executable, "-W", "always", "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert (out.returncode, out.stdout, out.stderr) == (0, "", "")


def test_nothing_reaches_stdout_or_stderr_from_a_check(capfd):
    check_hours(load_network("ieee33"), np.zeros((2, 33)))
    assert capfd.readouterr() == ("", "")
