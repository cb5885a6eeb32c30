"""Which route solves a stochastic schedule: the extensive form, the Benders decomposition, the decomposition in one
branch-and-bound tree (SCIP, an optional dependency), or "auto".

Kept apart from the solvers so the command line can name the routes without importing the solver stack.
"""

from __future__ import annotations

import importlib.util

METHODS = ("auto", "extensive", "benders", "tree")
# From this many scenarios "auto" decomposes: at 10 the extensive form is faster, from 15 on Benders (measured on
# the paper's case, docs/solver.md "Measurements").
AUTO_BENDERS_SCENARIOS = 15
SCIP_INSTALL = "pip install 'dmosim[scip]'"  # what the tree method needs (an optional dependency)


def resolve_method(method: str, scenarios: int) -> str:
    """The route "auto" stands for at this scenario count; the other methods are themselves."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    if method == "auto":
        return "benders" if scenarios >= AUTO_BENDERS_SCENARIOS else "extensive"
    return method


def check_available(method: str) -> str:
    """``method``, if this installation can solve by it: the tree method needs PySCIPOpt, an optional dependency
    (docs/solver.md), looked for without importing it; ValueError naming the install command otherwise."""
    if method == "tree" and importlib.util.find_spec("pyscipopt") is None:
        raise ValueError(f"method tree needs PySCIPOpt, which is not installed: {SCIP_INSTALL}")
    return method
