"""What one solve varies around a case: the award, the penalty or the announced rule's deviation cost, the cost
convention and the mismatch form."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from scenarios.horizon import HOURS, per_subperiod

Mismatch = Literal["positive-part", "big-m"]


@dataclass(frozen=True)
class DeviationCost:
    """What the announced settlement rule charges per hour for a deviation d = P_M - P^sch (MW), as the maximum of
    affine pieces: rate_t(d) = max_j slope[t, j] d + intercept[t, j] ($/h), convex in d. It generalises the paper's
    mismatch term c ΔP+ of (1) and (19)-(21), which is the pieces (0, 0) and (c, 0) in every hour."""

    slope: np.ndarray      # (24, J) $/MWh
    intercept: np.ndarray  # (24, J) $/h

    @classmethod
    def from_pieces(cls, hours: Sequence[Sequence[Sequence[float]]]) -> DeviationCost:
        """From 24 hourly lists of (slope, intercept) pieces, as an award carries them; hours with fewer pieces
        repeat their last one (which changes no maximum)."""
        if len(hours) != HOURS or not all(hours):
            raise ValueError(f"a deviation cost has {HOURS} hours of at least one piece each")
        width = max(len(h) for h in hours)
        table = np.array([[*h, *[h[-1]] * (width - len(h))] for h in hours], float)  # (24, J, 2)
        if not np.isfinite(table).all():
            raise ValueError("a deviation cost's pieces must be finite")
        return cls(table[:, :, 0], table[:, :, 1])

    def rate(self, d: np.ndarray) -> np.ndarray:
        """rate(d) per sub-period: ``d`` (..., 24 K), hour by hour."""
        k = d.shape[-1] // HOURS
        slope, intercept = per_subperiod(self.slope, k, axis=0), per_subperiod(self.intercept, k, axis=0)  # (24 K, J)
        return (d[..., None] * slope + intercept).max(axis=-1)

    def paper_rate(self) -> float | None:
        """c, when this is the paper's term c ΔP+ in every hour (pieces (0, 0) and (c, 0)); else None."""
        pieces = {tuple(sorted(set(zip(s, i)))) for s, i in zip(self.slope.tolist(), self.intercept.tolist())}
        if len(pieces) == 1:
            (hour,) = pieces
            if len(hour) == 2 and hour[0] == (0.0, 0.0) and hour[1][1] == 0.0 and hour[1][0] >= 0:
                return hour[1][0]
        return None


@dataclass(frozen=True)
class Params:
    """What a solve varies around the case: the award P^sch (24,), the penalty c, the cost convention. With
    ``deviation_cost``, the mismatch is priced by it instead of by c; with ``take_award``, the award is also a
    floor while connected (microgrid_agent/model/grid.py)."""

    p_sch: np.ndarray
    penalty: float
    cost_convention: str = "real"
    mismatch: Mismatch = "positive-part"
    import_price: np.ndarray | None = None  # (24,) $/MWh paid for P_M, for bidding (agent/bidding.py)
    deviation_cost: DeviationCost | None = None
    take_award: bool = False  # the award must be taken while connected: P_M >= P^sch too (model/grid.py)
