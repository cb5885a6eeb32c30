"""The microgrid: the paper's scheduling model (model/), the routes that solve it (solvers/), the result contract
(schedule.py) and its independent checker (checker.py), the agent process (agent/) and the paper's studies
(studies/). Imports ``scenarios`` and ``messages``, never ``dmo``."""
