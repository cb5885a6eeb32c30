"""What one solve varies around a case: the award, the penalty, the cost convention and the mismatch form."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Mismatch = Literal["positive-part", "big-m"]


@dataclass(frozen=True)
class Params:
    """What a solve varies around the case: the award P^sch (24,), the penalty c, the cost convention."""

    p_sch: np.ndarray
    penalty: float
    cost_convention: str = "real"
    mismatch: Mismatch = "positive-part"
    import_price: np.ndarray | None = None  # (24,) $/MWh paid for P_M, for bidding (agent/bidding.py)
