"""The branch-flow AC power flow (dmo/market/branchflow.py) against the closed form of a two-bus line, against
pandapower's Newton-Raphson on the IEEE 33-bus feeder, and its sensitivities and loss factors against finite
differences of its own solutions."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dmo.market.acflow import check_hours
from dmo.market.branchflow import BranchFlow
from scenarios.network import LOAD_PROFILE, build, load_network

PEAK = LOAD_PROFILE.index(1.0)


def test_a_two_bus_line_solves_the_quadratic():
    # 10 kV, z_base = 100 ohm: r = 0.02, x = 0.04 p.u.; the substation held at 1.02 p.u.
    net = build("two", 10.0, [{"name": "s"}, {"name": "a"}],
                [{"from": "s", "to": "a", "r_ohm": 2.0, "x_ohm": 4.0, "s_max_mva": 5.0}], "s")
    net = dataclasses.replace(net, v_substation=1.02)
    p, q, r, x, vs = 1.6, 0.95, 0.02, 0.04, 1.02
    point = BranchFlow(net).solve(np.array([0.0, p]), np.array([0.0, q]))
    # |V_s|^2 |V|^2 = |V|^4 + 2 (rP + xQ) |V|^2 + |z|^2 |S|^2, P and Q the load's: a quadratic in |V|^2
    b = vs ** 2 - 2 * (r * p + x * q)
    u = (b + math.sqrt(b ** 2 - 4 * (r ** 2 + x ** 2) * (p ** 2 + q ** 2))) / 2
    losses = r * (p ** 2 + q ** 2) / u
    assert point.u == pytest.approx((vs ** 2, u), rel=1e-13)
    assert point.losses == pytest.approx(losses, rel=1e-12)
    assert point.flow_p == pytest.approx([p + losses], rel=1e-13)
    assert point.flow_q == pytest.approx([q + x * (p ** 2 + q ** 2) / u], rel=1e-13)


@pytest.mark.slow  # pandapower
def test_every_hour_of_ieee33_is_pandapowers_ac_flow():
    net = load_network("ieee33", power_factor=0.9)
    rng = np.random.default_rng(3)
    microgrids = np.zeros((24, net.n_buses))
    microgrids[:, 1:] = rng.uniform(-0.1, 0.1, (24, net.n_buses - 1))
    checks = check_hours(net, microgrids)
    flow = BranchFlow(net)
    for h, check in enumerate(checks):
        p = net.fixed_p[h] + microgrids[h]
        point = flow.solve(p, net.fixed_q[h] + net.tan_phi * microgrids[h])
        assert np.abs(point.v - np.array(check.v_pu)).max() <= 1e-9
        assert point.losses == pytest.approx(check.losses_mw, abs=1e-9)
        assert math.fsum(p) + point.losses == pytest.approx(check.substation_mw, abs=1e-9)


def test_the_sensitivities_and_loss_factors_are_the_derivatives_of_the_solution():
    net = load_network("ieee33", power_factor=0.95)
    flow = BranchFlow(net)
    p, q = net.fixed_p[PEAK] * 1.3, net.fixed_q[PEAK] * 1.3
    point = flow.solve(p, q)
    lines = net.n_lines
    # four quantities, each of one kind: a line's P, another's Q, a third's current, the voltage below a fourth
    g = {name: np.zeros((lines, 4)) for name in ("g_p", "g_q", "g_l", "g_u")}
    g["g_p"][3, 0], g["g_q"][10, 1], g["g_l"][5, 2], g["g_u"][20, 3] = 1.0, 1.0, 1.0, 1.0
    adjoint = flow.adjoint(point)
    dp, dq = adjoint.sensitivities(**g)
    lf_p, lf_q, _, _ = adjoint.loss_factors()

    def quantities(pt):
        return np.array([pt.flow_p[3], pt.flow_q[10], pt.current2[5], pt.u[net.child[20]], pt.losses])

    eps = 1e-6
    for j in range(net.n_buses):
        e = np.eye(net.n_buses)[j] * eps
        by_p = (quantities(flow.solve(p + e, q)) - quantities(flow.solve(p - e, q))) / (2 * eps)
        by_q = (quantities(flow.solve(p, q + e)) - quantities(flow.solve(p, q - e))) / (2 * eps)
        assert np.abs(by_p - np.append(dp[:, j], lf_p[j])).max() <= 1e-8, j
        assert np.abs(by_q - np.append(dq[:, j], lf_q[j])).max() <= 1e-8, j
    assert lf_p[net.root] == lf_q[net.root] == 0.0 and (lf_p[1:] > 0).all()


def test_the_adjoint_does_not_depend_on_the_order_the_lines_are_listed_in():
    # the elimination renumbers the lines depth by depth: listed in any order, a feeder has the same sensitivities
    net = load_network("ieee33", power_factor=0.95)
    order = np.random.default_rng(5).permutation(net.n_lines)
    shuffled = dataclasses.replace(net, **{f: getattr(net, f)[order] for f in ("parent", "child", "r_ohm", "x_ohm",
                                                                                "s_max_mva")})
    p, q = net.fixed_p[PEAK] * 1.3, net.fixed_q[PEAK] * 1.3
    rng = np.random.default_rng(6)
    g = {name: rng.normal(size=(net.n_lines, 3)) for name in ("g_p", "g_q", "g_l", "g_u")}
    dp, dq = BranchFlow(net).adjoint(BranchFlow(net).solve(p, q)).sensitivities(**g)
    flow = BranchFlow(shuffled)
    dp_s, dq_s = flow.adjoint(flow.solve(p, q)).sensitivities(**{name: v[order] for name, v in g.items()})
    assert np.abs(dp_s - dp).max() <= 1e-12 and np.abs(dq_s - dq).max() <= 1e-12


def test_a_start_near_the_solution_finds_the_same_one_and_a_collapse_finds_none():
    net = load_network("ieee33")
    flow = BranchFlow(net)
    p, q = net.fixed_p[PEAK], net.fixed_q[PEAK]
    cold = flow.solve(p, q)
    warm = flow.solve(p, q, flow.solve(p * 1.01, q * 1.01))
    assert warm.sweeps < cold.sweeps
    assert np.abs(warm.u - cold.u).max() <= 1e-13 and warm.losses == pytest.approx(cold.losses, rel=1e-12)
    assert flow.solve(p * 20, q * 20) is None  # far past the feeder's voltage collapse
