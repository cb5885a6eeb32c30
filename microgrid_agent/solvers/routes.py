"""Which route solves a stochastic schedule: the extensive form, the Benders decomposition, the decomposition in one
branch-and-bound tree (SCIP, an optional dependency), or "auto".

Kept apart from the solvers so the command line can name the routes without importing the solver stack.
"""

from __future__ import annotations

import importlib.util

METHODS = ("auto", "extensive", "benders", "tree")
# From this many scenarios "auto" decomposes, by metering resolution: where Benders' median over scenario seeds beat
# the extensive form's on the paper's case (docs/notes/2026-11-27-auto-crossover.md).
AUTO_BENDERS_SCENARIOS = 10
AUTO_BENDERS_SCENARIOS_HOURLY = 90
SCIP_INSTALL = "pip install 'dmosim[scip]'"  # what the tree method needs (an optional dependency)


def auto_threshold(subperiods: int) -> int:
    """From how many scenarios "auto" decomposes at ``subperiods`` metering sub-periods per hour."""
    return AUTO_BENDERS_SCENARIOS_HOURLY if subperiods == 1 else AUTO_BENDERS_SCENARIOS


def auto_rule() -> str:
    """What "auto" does, in words, for help texts and docs."""
    return (f"benders from {AUTO_BENDERS_SCENARIOS} scenarios on ({AUTO_BENDERS_SCENARIOS_HOURLY} at hourly "
            "resolution), the extensive form below")


def resolve_method(method: str, scenarios: int, subperiods: int) -> str:
    """The route "auto" stands for at this scenario count and resolution; the other methods are themselves."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    if method == "auto":
        return "benders" if scenarios >= auto_threshold(subperiods) else "extensive"
    return method


def check_available(method: str) -> str:
    """``method``, if this installation can solve by it: the tree method needs PySCIPOpt, an optional dependency
    (docs/solver.md), looked for without importing it; ValueError naming the install command otherwise."""
    if method == "tree" and importlib.util.find_spec("pyscipopt") is None:
        raise ValueError(f"method tree needs PySCIPOpt, which is not installed: {SCIP_INSTALL}")
    return method
