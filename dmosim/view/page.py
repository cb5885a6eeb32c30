"""What the page shows, from what an observer has seen (``page(observed)``): a plain JSON-able dict, aggregated here
so that what goes to a browser stays small whatever the fleet (a few agents: a row each; more than
``DETAIL_AGENTS``: agents x hours matrices and the ranked bills, as the run's figure does, docs/recording.md).

Before an agent's statement comes, its bill is what has accrued: the energy charge of each hour metered (clearing
price x award) and, at the award's penalty and credit rates, the paper's deviation penalty and credit of its meter
readings (``accrued``); once the statement comes, the statement's figures replace them (``settled``: true).
"""

from __future__ import annotations

from scenarios.horizon import HOURS

from .state import MONEY, Day, Observed

DETAIL_AGENTS = 8  # more agents than this: heat maps and ranked bills, not a row each (as the figure's threshold)
RANKED_BILLS = 5  # the highest and lowest bills shown with many agents
SHOWN_INCIDENTS = 50  # the latest incidents sent to the page
SHOWN_WAITING = 20  # agents named as awaited; the rest counted


def _r(x: float | None, digits: int = 3) -> float | None:
    return None if x is None else round(float(x), digits)


def imports(day: Day, agent: str) -> list[float | None]:
    """The agent's metered import of each hour, MWh (the mean of its sub-periods' P_M x 1 h); None: not metered."""
    metered = day.meter.get(agent, {})
    return [None if h not in metered else sum(metered[h]) / len(metered[h]) for h in range(1, HOURS + 1)]


def accrued(day: Day, agent: str) -> dict[str, float]:
    """What the agent's metered hours have cost it so far, by the paper's rule at the award's rates (its statement's
    terms: energy charge, deviation penalty and credit, total), and the hours counted."""
    award, price = day.awards.get(agent), day.prices.get(agent)
    energy = penalty = credit = 0.0
    hours = 0
    for h, readings in day.meter.get(agent, {}).items():
        if award is None or price is None:
            break
        p_sch, dt = award[h - 1], 1.0 / len(readings)
        energy += price[h - 1] * p_sch
        penalty += day.penalty_rate * sum(max(p - p_sch, 0.0) for p in readings) * dt
        credit += day.credit_rate * sum(max(p_sch - p, 0.0) for p in readings) * dt
        hours += 1
    return {"energy_charge": energy, "deviation_penalty": penalty, "deviation_credit": credit,
            "total": energy + penalty - credit, "hours": hours}


def bill(observed: Observed, agent: str) -> dict:
    """The agent's bill so far: the days settled before plus today's statement, or what today has accrued."""
    day = observed.day
    statement = day.statements.get(agent) if day else None
    today = statement if statement is not None else (accrued(day, agent) if day else {k: 0.0 for k in MONEY})
    before = observed.settled_before.get(agent, {})
    return {**{k: _r(before.get(k, 0.0) + today[k], 2) for k in MONEY}, "settled": statement is not None}


def hourly_prices(day: Day) -> dict:
    """Per hour: the ISO's price, and the clearing prices (one on a copper plate; the lowest and highest bus price
    of the agents' buses on a feeder)."""
    prices = list(day.prices.values())
    low = [_r(min(p[h] for p in prices), 2) if prices else None for h in range(HOURS)]
    high = [_r(max(p[h] for p in prices), 2) if prices else None for h in range(HOURS)]
    return {"iso": [_r(x, 2) for x in day.iso_price], "clearing_low": low, "clearing_high": high,
            "congestion": list(day.congestion)}


def feeder(day: Day, hour: int | None) -> dict | None:
    """On a feeder: the bus x hour price map (as planned), and the voltage along the feeder and the line loadings of
    ``hour`` (as realised once metered, else as planned), its AC check's violations and binding lines."""
    f = day.feeder
    if f is None:
        return None
    prices = [[None] * HOURS for _ in f.buses]
    for (h, stage), hour_of in f.hours.items():
        if stage == "plan" and hour_of["bus_price_per_mwh"] is not None:
            for b, p in enumerate(hour_of["bus_price_per_mwh"]):
                prices[b][h - 1] = _r(p, 2)
    shown = hour or max((h for h, _ in f.hours), default=None)
    current = None
    if shown is not None:
        stage = "realised" if (shown, "realised") in f.hours else "plan"
        at = f.hours.get((shown, stage))
        if at is not None:
            current = {"hour": shown, "stage": stage, "voltage_pu": [_r(v, 4) for v in at["voltage_pu"]],
                       "line_loading": [_r(x, 3) for x in at["line_loading"]],
                       "binding_lines": at["binding_lines"], "violations": at["violations"],
                       "ac_v_min_pu": _r(at["ac_v_min_pu"], 4), "ac_max_loading": _r(at["ac_max_loading"], 3),
                       "converged": at["converged"]}
    return {"network": f.network, "buses": list(f.buses), "lines": list(f.lines), "bus_prices": prices,
            "current": current}


def page(observed: Observed) -> dict:
    """Everything the page shows, as JSON-able values."""
    day, clock = observed.day, observed.clock
    agents = sorted(set(observed.agents) | set(day.awards if day else ()))
    waiting = observed.waiting_for()
    out = {
        "run_token": observed.run_token, "messages": observed.messages, "last_ns": observed.last_ns,
        "clock": None if clock is None else {"phase": clock.phase, "hour": clock.hour, "day": clock.day,
                                             "days": clock.days, "deadline_s": clock.deadline_s, "at_ns": clock.at_ns},
        "market_day": day.market_day if day else None, "days_done": list(observed.days_done),
        "waiting_for": waiting[:SHOWN_WAITING], "waiting_count": len(waiting),
        "agent_count": len(agents), "rejected": observed.rejected,
        "incidents": observed.incidents[-SHOWN_INCIDENTS:][::-1], "incident_count": observed.incident_count,
        "hours": hourly_prices(day) if day else None, "feeder": feeder(day, clock.hour if clock else None) if day else None,
        "summary": day is not None and day.summary is not None,
    }
    if day is None:
        out.update(detail=[], compact=None)
        return out
    bills = {a: bill(observed, a) for a in agents}
    if len(agents) <= DETAIL_AGENTS:
        out["detail"] = [{"agent": a, "bus": day.bus_of.get(a) or observed.agents.get(a, {}).get("bus"),
                          "award": [_r(x) for x in day.awards[a]] if a in day.awards else None,
                          "price": [_r(x, 2) for x in day.prices[a]] if a in day.prices else None,
                          "import": [_r(x) for x in imports(day, a)], "bill": bills[a]} for a in agents]
        out["compact"] = None
        return out
    deviation, penalty = [], []
    for a in agents:
        award, metered = day.awards.get(a), imports(day, a)
        deviation.append([None if award is None or m is None else _r(m - award[h], 2) for h, m in enumerate(metered)])
        readings = day.meter.get(a, {})
        penalty.append([None if award is None or h not in readings else
                        _r(day.penalty_rate * sum(max(p - award[h - 1], 0.0) for p in readings[h]) / len(readings[h]), 1)
                        for h in range(1, HOURS + 1)])
    ranked = sorted(agents, key=lambda a: bills[a]["total"])
    pick = ranked[::-1][:RANKED_BILLS] + [a for a in ranked[:RANKED_BILLS] if a not in ranked[::-1][:RANKED_BILLS]]
    totals = [bills[a]["total"] for a in agents]
    out["detail"] = []
    out["compact"] = {"agents": agents, "deviation_mwh": deviation, "penalty": penalty,
                      "bills": [{"agent": a, **bills[a]} for a in pick],
                      "bills_total": _r(sum(totals), 2), "bills_mean": _r(sum(totals) / len(totals), 2),
                      "settled": sum(1 for a in agents if bills[a]["settled"])}
    return out
