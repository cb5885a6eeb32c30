"""Stochastic programming figures of a solved day: value of the stochastic solution and of perfect information.

RP is the stochastic (recourse) problem; EV the expected-value problem (one scenario of mean load, renewables
and connection); EEV the expected cost of EV's first-stage decisions over all scenarios; WS the wait-and-see
value, each scenario solved with its own first stage. VSS = EEV - RP >= 0 and EVPI = RP - WS >= 0 (Birge and
Louveaux, Introduction to Stochastic Programming, ch. 4).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from scenarios.generation import expected_value

from .instance import Instance
from .model import first_stage_of
from .schedule import StochasticSchedule
from .solvers.extensive import solve


@dataclass(frozen=True)
class StochasticMetrics:
    rp: float
    ev: float
    eev: float
    ws: float

    @property
    def vss(self) -> float:
        return self.eev - self.rp

    @property
    def evpi(self) -> float:
        return self.rp - self.ws

    def as_dict(self) -> dict[str, float]:
        return {**asdict(self), "vss": self.vss, "evpi": self.evpi}


def stochastic_metrics(inst: Instance, rp: StochasticSchedule, **options) -> StochasticMetrics:
    """VSS and EVPI for a solved instance; ``options`` (gap, time_limit) pass to every solve.

    With a nonzero gap each figure is within that gap of its exact value: RP and WS are MIP objectives, EEV is
    an LP once the first stage is fixed.
    """
    ev = solve(inst.case, expected_value(inst.scen), inst.params, **options)
    eev = solve(inst.case, inst.scen, inst.params, fixed=first_stage_of(ev), **options)
    ws = sum(
        p * solve(inst.case, inst.scen.single(s), inst.params, **options).objective
        for s, p in enumerate(inst.scen.probability)
    )
    return StochasticMetrics(rp=rp.objective, ev=ev.objective, eev=eev.objective, ws=float(ws))
