"""Routes to a solved stochastic schedule: the extensive form (extensive.py), the Benders decomposition
(benders.py, with its master's relaxation in relaxation.py), both on HiGHS (highs.py); which route "auto" takes
(routes.py); and the stochastic-programming figures VSS and EVPI (metrics.py)."""
