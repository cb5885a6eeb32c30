"""Market days from Python (docs/api.md): an experiment run as processes (the DMO, the agents, the recorder),
its result (a typed ``RunReport``), and its recording as pandas tables.

    python examples/market_days.py [OUT]     # two days of two tiny agents into OUT (default runs/<run_id>)
"""

import sys

from dmosim.experiment.spec import parse_experiment
from dmosim.launch.local import run_experiment
from dmosim.results.tables import open_recording

experiment = parse_experiment({
    "name": "two-days", "days": 2, "market_day": "2026-07-06", "seed": 3,
    "agents": {"count": 2}, "market": {"subperiods": 1, "penalty": 150.0},
    "schedule": {"scenarios": 1, "gap": 0.05},
    "profiles": {"load_scale": [1.0, 0.8]},  # the second day lighter
})
result = run_experiment(experiment, sys.argv[1] if len(sys.argv) > 1 else None, say=print)
print(f"run {result.run_id} in {result.run_dir}: {len(result.days)} days, {result.wall_s:.0f} s")

tables = open_recording(result.recording)
bills = tables["days"].pivot_table(index="market_day", columns="agent", values="total")
print("each agent's bill per day, $:")
print(bills.round(2).to_string())
for agent, days in result.realised.items():
    print(f"{agent}: own operating cost {sum(d.total for d in days):,.2f} $, "
          f"curtailed {sum(d.curtailment_mwh for d in days):.3f} MWh")
