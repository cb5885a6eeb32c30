"""A Jensen-type lower bound of the expected recourse, for the Benders master: scenario groups at mean data, hourly.

The scenario data (load, renewable availability, connection U) enter the second stage of objective (1) and
constraints (2)-(5), (8)-(9), (11)-(12), (15)-(16), (18)-(21) only as right-hand sides and bounds, and every
constraint is linear in (dispatch, data) for a fixed first stage x. So the probability-weighted mean of the
scenarios' optimal dispatches in a group g is a feasible dispatch of the group's mean data, at the mean cost:
E[Q(x, xi) | g] >= Q(x, E[xi | g]) (Jensen). Averaging a 10-minute dispatch over each hour is likewise feasible
for the hourly model (K = 1) at hour-averaged data: balance (2), limits (3), (8)-(9), (15), (18) and the
mismatch dP+ >= P_M - P^sch (19) are linear within a sub-period; the hourly ramp (4)-(5) bounds a difference of
hour means, which is a mean of K differences each spanning K steps and one hour start, so within UR + P_min y;
(11) holds for the end-of-hour energy; (16) sums the same energy. Hence, for every x,

    sum_{s in g} p_s Q_s(x) >= p_g Q_hourly(x, mean data of g).

Grouping by islanding pattern keeps U at 0/1 in every group's mean, so (18) stays as tight as in the scenarios.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cvxpy as cp
import numpy as np

from scenarios import exact
from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import HOURS

from ..model import Index, Params, recourse, second_stage_constraints
from ..schedule import energy_weight


def islanding_groups(scen: ScenarioSet) -> np.ndarray:
    """(S,) group label of each scenario: scenarios with the same connection pattern U share a group."""
    _, label = np.unique(scen.connected, axis=0, return_inverse=True)
    return label.ravel()


def membership(scen: ScenarioSet, label: np.ndarray) -> np.ndarray:
    """(groups, S) with p_s where scenario s belongs to group g, else 0; its row sums are the p_g."""
    out = np.zeros((label.max() + 1, scen.S))
    out[label, np.arange(scen.S)] = scen.probability
    return out


def group_means(scen: ScenarioSet, label: np.ndarray) -> ScenarioSet:
    """One hourly scenario per group: the data averaged over each hour and over the group (weights p_s / p_g)."""
    weight = membership(scen, label)
    p_g = weight.sum(axis=1)
    weight = weight / p_g[:, None]

    def hourly(data: np.ndarray) -> np.ndarray:
        return data.reshape(*data.shape[:-1], HOURS, scen.subperiods).mean(axis=-1)

    return ScenarioSet(subperiods=1, probability=p_g, load=exact.weighted(weight, hourly(scen.load), 0),
                       renewable=exact.weighted(weight, hourly(scen.renewable), 1),
                       connected=exact.weighted(weight, hourly(scen.connected), 0))


@dataclass
class GroupRelaxation:
    """The groups' hourly second stage as constraints on shared first-stage variables, and each group's cost."""

    constraints: list[cp.Constraint]
    cost: cp.Expression  # (groups,) Q_hourly(x, mean data of g), in the scenarios' cost units
    membership: np.ndarray  # (groups, S)
    probability: np.ndarray  # (groups,) p_g

    def linking(self, theta: cp.Expression) -> cp.Constraint:
        """sum_{s in g} p_s theta_s >= p_g cost_g: the relaxation bounds each group's share of the recourse."""
        return self.membership @ theta >= cp.multiply(self.probability, self.cost)


def relaxed(params: Params) -> Params:
    """The parameters the relaxation is built with: the mismatch as the positive part (equal optimum to the big-M
    form, docs/model.md), so that it stays an LP."""
    return replace(params, mismatch="positive-part")


def group_relaxation(case: Case, scen: ScenarioSet, params: Params, v: dict, label: np.ndarray) -> GroupRelaxation:
    """The relaxation over variables ``v`` of ``model.variables(case, groups, HOURS, params=relaxed(params))``.

    The mismatch is modelled as the positive part (equal optimum to the big-M form, docs/model.md), so the
    relaxation stays an LP. Energy costs are rescaled so that an hour of the relaxation costs what K sub-periods
    of the same mean power cost in ``params.cost_convention``.
    """
    means = group_means(scen, label)
    ix = Index(means.S, 1)
    params = relaxed(params)
    K = scen.subperiods
    scale = energy_weight(K, params.cost_convention) * K / energy_weight(1, params.cost_convention)
    cost = cp.hstack([scale * sum(recourse(case, replace(means, probability=one), params, ix, v).values())
                      for one in np.eye(means.S)])
    return GroupRelaxation(second_stage_constraints(case, means, params, ix, v), cost, membership(scen, label),
                           means.probability)
