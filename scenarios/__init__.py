"""The data of the market: microgrid cases (case.py), their uncertainty as scenario sets (generation.py,
reduction.py), fleets of microgrids (fleet.py), the day's hours (horizon.py) and the naming rule of processes
(names.py). The bottom of the import flow: it imports none of the other three packages."""
