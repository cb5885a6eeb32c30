"""A settlement rule of one's own that reads the grid (docs/settlement.md, "Writing a rule"): the paper's rule, but
no penalty and no credit for what the grid imposed. In a sub-period the DMO islanded (its grid_state said
``connected`` false) a microgrid must meter P_M = 0 whatever its award, so a deviation there is the grid's doing,
not the agent's.

    dmosim settle runs/<run_id> --rule paper --rule examples/islanding_rule.py:islanding_exempt
    python examples/islanding_rule.py      # settles a small synthetic day under both rules

``day.grid`` holds the 24 hours' grid states as the DMO published them (None when a recording lacks them: then the
rule is the paper's).
"""

from dataclasses import replace

from dmo.market.rules import BUILT_IN, Charges, SettlementDay


def islanding_exempt(day: SettlementDay, penalty: float = 150.0, credit: float = 0.0) -> dict[str, list[Charges]]:
    """The paper's rule at ``penalty`` and ``credit`` ($/MWh), each sub-period the grid islanded settled as if the
    agent had met its award: neither penalty nor credit there (a missing one included)."""
    if day.grid is None:
        return BUILT_IN["paper"](day, penalty=penalty, credit=credit)
    met = {agent: {h: [award[h] if not up else p for p, up in zip(day.readings(agent, h), day.grid[h].connected)]
                   for h in range(len(award)) if h in day.meter.get(agent, {}) or day.grid[h].islanded}
           for agent, award in day.awards.items()}
    return BUILT_IN["paper"](replace(day, meter=met), penalty=penalty, credit=credit)


if __name__ == "__main__":
    from dmo.market.choice import choose, trial_day

    day = trial_day()
    for spec in ("paper", f"{__file__}:islanding_exempt"):
        statements, totals = choose(spec).settle(day)
        print(f"{spec.rpartition('/')[2]:<36} penalties " + ", ".join(
            f"{a} ${st.deviation_penalty}" for a, st in statements.items()) + f"; all agents ${totals.total}")
