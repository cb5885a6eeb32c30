"""How many threads every HiGHS solve in a dmosim process may use: the agent's routes and the DMO's quadratic
programs alike (a module of its own, so that the DMO reads it without loading the routes' cvxpy)."""

# The threads of every HiGHS solve: left at 0, HiGHS searches with as many workers as the process has cores, and the
# tree it searches depends on them, so a search would take another path on another machine
# (docs/notes/2026-12-08-highs-one-thread.md). The count is HiGHS's per OS thread, not per model: it starts one
# scheduler per thread at its first solve's count and refuses a later solve there that asks for another, so every
# HiGHS we make, the agent's and the DMO's, is given this one (docs/solver.md, "The same path on every machine").
HIGHS_THREADS = 1
