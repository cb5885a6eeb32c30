"""Whether a run repeated from a recording (``dmosim run --from``) settled every agent as the recorded one did: the
statements of both, compared day by day, agent by agent and hour by hour, to the cent."""

from __future__ import annotations

from messages.recording import Recording


def statements_of(rec: Recording) -> dict[tuple[str, str], object]:
    """(market day, agent) -> the first settlement statement recorded for them."""
    out: dict[tuple[str, str], object] = {}
    for _, msg in rec.decoded("settlement_statement"):
        out.setdefault((msg.market_day, msg.agent), msg)
    return out


def differences(before: Recording, again: Recording) -> list[str]:
    """Every agent, day and hour whose settlement differs between the two recordings, one line each; empty when
    every statement is the same to the cent."""
    old, new = statements_of(before), statements_of(again)
    out = []
    for day, agent in sorted(set(old) | set(new)):
        if (day, agent) not in new or (day, agent) not in old:
            out.append(f"{agent} {day}: a statement {'only before' if (day, agent) in old else 'only now'}")
            continue
        a, b = old[day, agent], new[day, agent]
        for line_a, line_b in zip(a.lines, b.lines):
            changed = [name for name in ("energy_charge", "deviation_penalty", "deviation_credit", "total",
                                         "missing_subperiods") if getattr(line_a, name) != getattr(line_b, name)]
            if changed:
                out.append(f"{agent} {day} hour {line_a.hour}: " + ", ".join(
                    f"{name} {getattr(line_a, name)!r} then, {getattr(line_b, name)!r} now" for name in changed))
    return out
