"""How many threads every HiGHS solve in a dmosim process may use: the agent's routes and the DMO's quadratic
programs alike (a module of its own, so that the DMO reads it without loading the routes' cvxpy)."""

# The threads of every HiGHS solve, so that a search takes the same path on any machine. Left at its default (0),
# HiGHS 1.16 runs a MIP with as many workers as the cores the process may use ("using up to 2 workers across 2
# threads" here, 1 under `taskset -c 0`), and the tree it searches depends on them: a 12-scenario hourly day's
# certifying master took 7 nodes on one core and 3 on two. For a given count the search is the same on any cores;
# with 1, HiGHS never uses more than one thread, and it was no slower than 2 here. The option is not one model's:
# HiGHS starts one scheduler for each OS thread that solves, at its first solve's count, and refuses a later solve
# on that thread that asks for another, so every HiGHS we make, the agent's and the DMO's, is given this one
# (docs/solver.md, "The same path on every machine").
HIGHS_THREADS = 1
