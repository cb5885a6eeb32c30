"""A settlement rule of one's own (docs/settlement.md, "Writing a rule"): the paper's penalty, but no agent pays
more than ``cap`` dollars of penalty in a day.

    dmosim settle runs/<run_id> --rule paper --rule examples/settlement_rule.py:capped_penalty:cap=200
    python examples/settlement_rule.py      # settles a small synthetic day under both rules

A rule is a function of a ``SettlementDay`` and its parameters (numbers) that returns, for each awarded agent, 24
``Charges``: the hour's energy charge, penalty and credit in dollars. dmosim rounds each to the cent once, sums the
lines into the statement, and refuses a rule whose money is not finite, or whose totals do not add up.
"""

from fractions import Fraction

from dmo.market.rules import BUILT_IN, Charges, SettlementDay


def capped_penalty(day: SettlementDay, penalty: float = 150.0, credit: float = 0.0,
                   cap: float = 500.0) -> dict[str, list[Charges]]:
    """The paper's rule at ``penalty`` and ``credit`` ($/MWh), each agent's penalty capped at ``cap`` $ a day: the
    hours are charged in order until the cap is used up. A missing sub-period is settled as the paper settles it."""
    out = {}
    for agent, hours in BUILT_IN["paper"](day, penalty=penalty, credit=credit).items():
        left = Fraction(cap)
        out[agent] = []
        for hour in hours:
            charged = min(Fraction(hour.penalty), left)
            left -= charged
            out[agent].append(Charges(energy_charge=hour.energy_charge, penalty=charged, credit=hour.credit))
    return out


if __name__ == "__main__":
    from dmo.market.choice import choose, trial_day

    day = trial_day()
    for spec in ("paper", f"{__file__}:capped_penalty:cap=20"):
        statements, totals = choose(spec).settle(day)
        print(f"{spec.rpartition('/')[2]:<36} penalties " + ", ".join(
            f"{a} ${st.deviation_penalty}" for a, st in statements.items()) + f"; all agents ${totals.total}")
