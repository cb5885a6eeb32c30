"""Which route solves a stochastic schedule: the extensive form, the Benders decomposition, or "auto".

Kept apart from the solvers so the command line can name the routes without importing the solver stack.
"""

from __future__ import annotations

METHODS = ("auto", "extensive", "benders")
# From this many scenarios "auto" decomposes: at 10 the extensive form is faster, from 15 on Benders (measured on
# the paper's case, docs/solver.md "Measurements").
AUTO_BENDERS_SCENARIOS = 15


def resolve_method(method: str, scenarios: int) -> str:
    """The route "auto" stands for at this scenario count; the other methods are themselves."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, not {method!r}")
    if method == "auto":
        return "benders" if scenarios >= AUTO_BENDERS_SCENARIOS else "extensive"
    return method
