"""One microgrid's stochastic day-ahead schedule from Python (docs/api.md): the paper's case against its Table I
award, solved, checked by the independent checker, and shown as tables.

    python examples/solve_one.py            # a few seconds: 3 scenarios, hourly
"""

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import make_instance
from scenarios.case import load_case

inst = make_instance(load_case("paper"), scenarios=3, subperiods=1, island_hours=1, seed=0)
schedule = inst.solve(method="auto", gap=0.01, time_limit=60)
report = check_schedule(inst.case, inst.scen, schedule, p_sch=inst.params.p_sch)
assert report.ok, report.summary(5)

print(f"{schedule.status}: expected cost ${schedule.objective:,.2f} (gap {schedule.mip_gap:.2%}), "
      f"{schedule.scenarios} scenarios, checked: every constraint holds")
print("cost by term, $:", {k: round(v, 2) for k, v in schedule.cost.as_dict().items()})
print("unit commitment (1 = on), hours 1..24:")
print(schedule.commitment.to_string())
print("scenario 0, first six hours:")
print((schedule.dispatch_frame(0).head(6).round(3) + 0.0).to_string())  # + 0.0: no "-0.0"
