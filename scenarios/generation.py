"""Scenario sets of the uncertain data: sub-hourly forecast errors of fixed load and renewables, and islanding."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HOURS = 24


@dataclass(frozen=True)
class ScenarioSet:
    """S scenarios at K sub-periods per hour (N = 24 K), with probabilities pr_s of objective (1).

    ``load`` (S, N): fixed load, MW. ``renewable`` (R, S, N): availability of each renewable, MW (ordered as
    the case's renewables). ``connected`` (S, N): U of (18), 1 grid-connected and 0 islanded.
    """

    subperiods: int
    probability: np.ndarray
    load: np.ndarray
    renewable: np.ndarray
    connected: np.ndarray

    @property
    def S(self) -> int:
        return len(self.probability)

    @property
    def N(self) -> int:
        return HOURS * self.subperiods

    @property
    def dt(self) -> float:
        return 1.0 / self.subperiods
