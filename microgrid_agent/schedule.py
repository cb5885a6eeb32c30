"""The typed result of a stochastic schedule: first-stage decisions, per-scenario dispatch, costs, bound and timings.

This module is the contract between the solvers (which fill it) and everything that reads a schedule: the
independent checker, the CLI, the studies and the agent. It holds data only, no model code.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from scenarios.horizon import HOURS, subperiod_hours

COST_CONVENTIONS = ("real", "paper")


def start_indicators(state: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """max(0, x_t - x_{t-1}) per row of a (M, 24) 0/1 state, with x_0 = ``initial`` (M,): where the state starts
    (a unit's start-ups from I, its shut-downs from 1 - I)."""
    before = np.concatenate([np.asarray(initial, float).reshape(-1, 1), state[:, :-1]], axis=1)
    return np.maximum(state - before, 0.0)


def energy_weight(subperiods: int, convention: str) -> float:
    """Weight of a MW-valued cost rate per sub-period in objective (1).

    ``real``: MW x dt hours, so costs are in dollars of energy. ``paper``: objective (1) as printed sums
    F(P) over sub-periods with no dt, which makes energy costs K times larger at K sub-periods per hour;
    offered so results can be set beside the paper's $39,566 (see docs/model.md).
    """
    if convention == "real":
        return subperiod_hours(subperiods)
    if convention == "paper":
        return 1.0
    raise ValueError(f"cost convention must be one of {COST_CONVENTIONS}, not {convention!r}")


@dataclass(frozen=True)
class CostBreakdown:
    """Expected daily cost of objective (1), split by term ($)."""

    generation: float
    startup: float
    curtailment: float
    penalty: float
    energy: float = 0.0  # grid energy at a given import price: only the bidding model prices it

    @property
    def total(self) -> float:
        return self.generation + self.startup + self.curtailment + self.penalty + self.energy

    def as_dict(self) -> dict[str, float]:
        out = {"generation": self.generation, "startup": self.startup,
               "curtailment": self.curtailment, "penalty": self.penalty}
        return out | ({"energy": self.energy} if self.energy else {})


@dataclass(frozen=True)
class FirstStage:
    """Hourly decisions shared by all scenarios (0/1 arrays).

    ``commitment`` I (G, 24), ``startup``/``shutdown`` (G, 24) with startup[g, t] = max(0, I[g,t] - I[g,t-1]),
    ``discharging`` u (24,), ``charging`` v (24,) of (8)-(10), ``load_on`` z (D, 24) of (15).
    """

    commitment: np.ndarray
    startup: np.ndarray
    shutdown: np.ndarray
    discharging: np.ndarray
    charging: np.ndarray
    load_on: np.ndarray


@dataclass(frozen=True)
class Dispatch:
    """Second-stage values per scenario s and sub-period n (n = (t-1)K + tau - 1), in MW or MWh.

    ``p_unit`` (G,S,N); ``p_renewable`` (R,S,N) used (availability minus spill); ``p_storage`` (S,N), positive
    when discharging; ``soc`` (S,N) stored energy C at the end of each sub-period; ``d_load`` (D,S,N);
    ``p_m`` (S,N) main grid transfer; ``load_shed`` (S,N) LS; ``dp_plus`` (S,N) positive mismatch.
    """

    p_unit: np.ndarray
    p_renewable: np.ndarray
    p_storage: np.ndarray
    soc: np.ndarray
    d_load: np.ndarray
    p_m: np.ndarray
    load_shed: np.ndarray
    dp_plus: np.ndarray


@dataclass(frozen=True)
class Timings:
    build_s: float
    solve_s: float
    total_s: float

    def as_dict(self) -> dict[str, float]:
        return {"build_s": self.build_s, "solve_s": self.solve_s, "total_s": self.total_s}


@dataclass(frozen=True)
class StochasticSchedule:
    """A solved stochastic day-ahead schedule.

    ``objective`` is the expected cost of the returned schedule, ``bound`` a valid lower bound on the optimum,
    ``mip_gap`` = (objective - bound) / |objective|.
    """

    status: str
    objective: float
    bound: float
    cost: CostBreakdown
    first: FirstStage
    dispatch: Dispatch
    probability: np.ndarray
    subperiods: int
    penalty: float
    cost_convention: str
    timings: Timings
    unit_names: tuple[str, ...]
    load_names: tuple[str, ...]
    extra: dict = field(default_factory=dict)
    take_award: bool = False  # solved with the award as a floor too (Params.take_award)

    @property
    def scenarios(self) -> int:
        return len(self.probability)

    @property
    def mip_gap(self) -> float:
        if not np.isfinite(self.bound):
            return float("inf")
        return max(0.0, self.objective - self.bound) / max(abs(self.objective), 1e-9)

    def _hourly(self, rows: np.ndarray, names) -> pd.DataFrame:
        frame = pd.DataFrame(np.rint(rows).astype(int).T, columns=list(names))
        frame.index = pd.RangeIndex(1, HOURS + 1, name="hour")
        return frame

    @property
    def commitment(self) -> pd.DataFrame:
        """Hour x unit commitment I (0/1)."""
        return self._hourly(self.first.commitment, self.unit_names)

    @property
    def storage_mode(self) -> pd.DataFrame:
        """Hour x (charging v, discharging u)."""
        return self._hourly(np.vstack([self.first.charging, self.first.discharging]), ("charging", "discharging"))

    @property
    def load_state(self) -> pd.DataFrame:
        """Hour x adjustable load state z (0/1)."""
        return self._hourly(self.first.load_on, self.load_names)

    def dispatch_frame(self, scenario: int, renewable_names=("wind", "solar")) -> pd.DataFrame:
        """One scenario's sub-period dispatch, indexed by (hour, sub-period)."""
        d, k = self.dispatch, self.subperiods
        n = d.p_m.shape[1]
        index = pd.MultiIndex.from_arrays([np.arange(n) // k + 1, np.arange(n) % k + 1], names=("hour", "subperiod"))
        cols = {name: d.p_unit[g, scenario] for g, name in enumerate(self.unit_names)}
        cols |= {name: d.p_renewable[r, scenario] for r, name in enumerate(renewable_names[: d.p_renewable.shape[0]])}
        cols |= {"storage": d.p_storage[scenario], "soc": d.soc[scenario]}
        cols |= {name: d.d_load[j, scenario] for j, name in enumerate(self.load_names)}
        cols |= {"p_m": d.p_m[scenario], "load_shed": d.load_shed[scenario], "dp_plus": d.dp_plus[scenario]}
        return pd.DataFrame(cols, index=index)

    def summary(self) -> dict:
        """The JSON object of ``dmosim solve --json`` (README, "Commands")."""
        return {
            "status": self.status,
            "objective": self.objective,
            "cost_breakdown": self.cost.as_dict(),
            "commitment": {name: self.commitment[name].tolist() for name in self.unit_names},
            "storage_mode": {col: self.storage_mode[col].tolist() for col in ("charging", "discharging")},
            "adjustable_loads": {name: self.load_state[name].tolist() for name in self.load_names},
            "mip_gap": self.mip_gap,
            "bound": self.bound,
            "scenarios": self.scenarios,
            "subperiods": self.subperiods,
            "penalty": self.penalty,
            "take_award": self.take_award,
            "cost_convention": self.cost_convention,
            "timings": self.timings.as_dict(),
            **self.extra,
        }
