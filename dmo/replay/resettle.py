"""Re-settle a recorded day from its recording alone and compare the result with the recorded statements, line by line.

What the DMO settled on is read back from the recording: the awards (P_sch, clearing prices and the settlement
terms: penalty, credit, sub-periods, rules version), the registrations (each agent's max import, the P_M assumed
for a missing sub-period) and the meter reports the DMO accepted: those whose SHA-256 its receipts to their
sender accepted, so that nothing the DMO refused, or never took up (its sender over its budget), counts, whatever
else a participant put on the wire; of those the first report per agent and hour counts, as the DMO counts it. A
recording of before receipts says only what the DMO refused, by a ``Rejection`` naming the key and SHA-256: of the
copies of one payload on one key, as many are left out as there were rejections (identical payloads settle
identically, so which copies does not matter).
"""

from __future__ import annotations

import collections
import hashlib
from dataclasses import dataclass, field
from typing import Iterator

from messages import (Award, GridState, MeterReport, Registration, SettlementStatement, encode, relative_key,
                      sender_matches_key)
from messages.recording import RecordedMessage, Recording
from scenarios.days import market_days as scenario_days
from scenarios.horizon import HOURS

from ..market.choice import ChosenRule, Trust, UntrustedRule, paper_rule
from ..market.settlement import RULES_VERSION, Statement, accepted_day
from ..operator.outbox import statement_message

STATEMENT_FIELDS = ("penalty_per_mwh", "credit_per_mwh", "rules_version", "settlement_rule", "energy_charge",
                    "deviation_penalty", "deviation_credit", "total", "missing_subperiods")


class ResettleError(ValueError):
    """A recording that cannot be re-settled (no awards, terms that differ between agents...): one line."""


@dataclass
class RecordedDay:
    """What settlement needs, as recorded."""

    market_day: str
    awards: dict[str, Award]
    registered: dict[str, Registration]   # each agent's registration: its import and export limits
    meter: dict[str, dict[int, tuple[float, ...]]]
    statements: dict[str, SettlementStatement]
    summary_totals: dict[str, dict] | None
    left_out: int = 0                      # meter reports left out because the DMO refused them
    grid: list[GridState] | None = None     # the 24 hours' grid states, None if the recording lacks one
    notes: list[str] = field(default_factory=list)

    @property
    def terms(self) -> Award:
        return next(iter(self.awards.values()))

    def prices(self, agents=None) -> tuple[tuple[float, ...], dict[str, tuple[float, ...]] | None]:
        """The day's clearing prices as its awards carry them and settlement reads them (``accepted_day``): on the
        copper plate one set for all (and None), on a feeder the substation's and each agent's own bus's."""
        terms = self.terms
        if terms.bus is None:
            return terms.clearing_price_per_mwh, None
        return terms.energy_price_per_mwh, {a: self.awards[a].clearing_price_per_mwh for a in agents or self.awards}


def recording_days(rec: Recording) -> list[str]:
    """The market days the recording is of, in order: as its metadata says (``dmosim run`` writes the first day and
    how many), else as the DMO's clock messages say. Messages of other days (anyone on the network may publish
    them) take no part in its settlement."""
    first, days = rec.metadata.get("market_day"), rec.metadata.get("days", "1")
    if first:
        try:
            return list(scenario_days(first, int(days)))
        except ValueError:
            pass  # metadata not written by dmosim: the clock messages say
    seen: dict[str, None] = {}
    for _, msg in day_messages(rec, None, "clock"):
        seen.setdefault(msg.market_day)
    return list(seen)


def held_days(rec: Recording) -> list[str]:
    """Of ``recording_days``, those the DMO's messages in the recording reach (a recording cut mid-run holds the
    first days only)."""
    held = {msg.market_day for kind in ("clock", "award", "settlement_statement")
            for _, msg in day_messages(rec, None, kind)}
    return [day for day in recording_days(rec) if day in held]


def day_messages(rec: Recording, day: str | None, kind: str) -> Iterator[tuple[RecordedMessage, object]]:
    """The valid messages of one kind as the receivers read them, one at a time (``Recording.decoded``): of this
    day, and from the key's owner to the key's addressee."""
    return ((m, msg) for m, msg in rec.decoded(kind)
            if (day is None or msg.market_day == day) and sender_matches_key(m.key, msg))


def gaps(rec: Recording) -> list[str]:
    """What re-settling the recording's days needs that it lacks, one line each (each starting with its market day
    when the recording is of several); empty when nothing is missing."""
    days = recording_days(rec)
    if len(days) <= 1:
        return day_gaps(rec, days[0] if days else None)
    return [f"{day}: {gap}" for day in days for gap in day_gaps(rec, day)]


def day_gaps(rec: Recording, day: str | None) -> list[str]:
    """What re-settling ``day`` needs that the recording lacks. A meter report is missing when the agent's recorded
    statement settled that hour as metered, yet no report for it is recorded; an hour the statement settled as
    missing was not reported at all, which is no gap. Agents register once a run, on its first day."""
    awarded = {msg.agent for _, msg in day_messages(rec, day, "award")}
    registered = {msg.sender for _, msg in day_messages(rec, None, "registration")}
    statements = {}
    for _, msg in day_messages(rec, day, "settlement_statement"):
        statements.setdefault(msg.agent, msg)
    metered: dict[str, set[int]] = {}
    for _, msg in day_messages(rec, day, "meter_report"):
        metered.setdefault(msg.sender, set()).add(msg.hour)
    named = {a for a in rec.metadata.get("agents", "").split(",") if a}
    out = [] if awarded else ["no award recorded"]
    for agent in sorted(named | awarded | registered | set(statements)):
        lacks = [what for what, present in (("registration", registered), ("award", awarded),
                                            ("statement", statements)) if agent not in present]
        if lacks:
            out.append(f"{agent}: no {', no '.join(lacks)} recorded")
        if agent in statements:
            hours = [line.hour for line in statements[agent].lines
                     if not line.missing and line.hour not in metered.get(agent, ())]
            if hours:
                out.append(f"{agent}: no meter report recorded for hour(s) {hour_ranges(hours)}, which its statement "
                           "settled as metered")
    if next(day_messages(rec, day, "day_summary"), None) is None:
        out.append("no day summary recorded")
    return out


def hour_ranges(hours: list[int]) -> str:
    """1, 2, 3, 5 -> "1-3, 5"."""
    runs: list[list[int]] = []
    for h in sorted(hours):
        if runs and h == runs[-1][-1] + 1:
            runs[-1].append(h)
        else:
            runs.append([h])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)


def recorded_day(rec: Recording, day: str | None = None) -> RecordedDay:
    """What settling ``day`` (default: the recording's first market day) needs, as recorded."""
    day = day or next(iter(recording_days(rec)), None)

    def decoded(kind: str) -> Iterator:
        return day_messages(rec, day, kind)

    awards: dict[str, Award] = {}
    for _, msg in decoded("award"):
        awards.setdefault(msg.agent, msg)  # the DMO awards each agent once
    if not awards:
        raise ResettleError(f"{rec.path}: no awards recorded" + (f" for {day}" if day else "")
                            + (f" ({rec.cut_note})" if rec.cut_note else ""))
    first = next(iter(awards.values()))
    # On a feeder each agent has its own bus's prices; the substation's are common to all.
    common = "clearing_price_per_mwh" if first.bus is None else "energy_price_per_mwh"
    for a in awards.values():
        if (a.bus is None) != (first.bus is None):
            raise ResettleError(f"{rec.path}: the award of {first.agent} and that of {a.agent} disagree on whether "
                                "the day was cleared on a feeder")
        for name in ("penalty_per_mwh", "credit_per_mwh", "subperiods", "rules_version", common, "settlement_rule"):
            if getattr(a, name) != getattr(first, name):
                raise ResettleError(f"{rec.path}: the awards of {first.agent} and {a.agent} differ in {name}")
    if first.rules_version != RULES_VERSION:
        raise ResettleError(f"{rec.path}: settlement rules version {first.rules_version}; this dmosim settles by "
                            f"version {RULES_VERSION}")

    registered: dict[str, Registration] = {}
    for _, msg, refused in _judged(rec, "registration", None):  # registered on the run's first day
        if not refused:
            registered.setdefault(msg.sender, msg)
    meter: dict[str, dict[int, tuple[float, ...]]] = {a: {} for a in awards}
    reports, left_out = accepted_meter_reports(rec, first.market_day, agents=set(awards), subperiods=first.subperiods)
    for _, msg in reports:
        meter[msg.sender][msg.hour - 1] = msg.p_m_mw
    missing = sorted(set(awards) - set(registered))
    if missing:
        raise ResettleError(f"{rec.path}: no registration recorded for {', '.join(missing)}, so no max import to "
                            "settle missing meter data by")
    statements = {}
    for _, msg in decoded("settlement_statement"):
        statements.setdefault(msg.agent, msg)
    summaries = list(decoded("day_summary"))
    totals = {a: t.model_dump() for a, t in summaries[-1][1].totals.items()} if summaries else None
    grids: dict[int, GridState] = {}
    for _, msg in decoded("grid_state"):
        grids.setdefault(msg.hour, msg)  # the DMO sends each hour's once (a copy is the same)
    grid = [grids[h] for h in range(1, HOURS + 1)] if len(grids) == HOURS else None
    return RecordedDay(first.market_day, awards, registered, meter, statements, totals, left_out, grid=grid)


def accepted_messages(rec: Recording, kind: str,
                      day: str | None = None) -> tuple[list[tuple[RecordedMessage, object]], int]:
    """The valid messages of one kind the DMO did not refuse, in log order, and how many it refused: of ``day``
    (every day if None), from the key's owner; of the copies of one payload on one key, as many are left out as
    there are recorded rejections of it."""
    kept, left_out = [], 0
    for m, msg, refused in _judged(rec, kind, day):
        if refused:
            left_out += 1
        else:
            kept.append((m, msg))
    return kept, left_out


def accepted_meter_reports(rec: Recording, day: str | None = None, *, agents: set[str] | None = None,
                           subperiods: int | None = None) -> tuple[list[tuple[RecordedMessage, MeterReport]], int]:
    """The meter reports the DMO accepted, in log order, and how many it refused (``accepted_messages``): of what
    it did not refuse, of ``agents`` (all if None) with ``subperiods`` readings (any if None), the first report per
    market day, agent and hour counts, as the DMO counts it. Only those are held, however many were recorded."""
    accepted: dict[tuple[str, str, int], tuple[RecordedMessage, MeterReport]] = {}
    left_out = 0
    for m, msg, refused in _judged(rec, "meter_report", day):
        if refused:
            left_out += 1
        elif (agents is None or msg.sender in agents) and (subperiods is None or msg.subperiods == subperiods):
            accepted.setdefault((msg.market_day, msg.sender, msg.hour), (m, msg))
    return list(accepted.values()), left_out


def _judged(rec: Recording, kind: str, day: str | None) -> Iterator[tuple[RecordedMessage, object, bool]]:
    """``day_messages``, each with whether the DMO refused it. What the DMO took is what it receipted as accepted
    (the SHA-256 of the payload as received, from its sender): a payload it never saw (one the network lost on its
    way to the DMO, or dropped unread, its sender over its budget) or refused is not. A recording of before
    receipts (protocol 3 and older) says only what the DMO refused: each recorded rejection uses up one copy."""
    accepted = rec.receipted
    refused = _refused(rec) if accepted is None else None
    for m, msg in day_messages(rec, day, kind):
        if accepted is not None:
            yield m, msg, (msg.sender, hashlib.sha256(m.payload).hexdigest()) not in accepted
        else:
            yield m, msg, _take(refused, m.relative_key, m.payload, msg)


def _refused(rec: Recording) -> collections.Counter:
    """(key, sha256) -> how many payloads the DMO refused, from its recorded rejections."""
    prefix = rec.prefix
    out: collections.Counter = collections.Counter()
    for _, msg in rec.decoded("rejection"):
        out[relative_key(msg.key, prefix), msg.payload_sha256] += 1
    return out


def _take(refused: collections.Counter, key: str, payload: bytes, msg) -> bool:
    """Whether this payload is one the DMO refused (using up one rejection). The DMO hashes either the payload as
    received or, when it refuses a valid message, the message re-encoded; both are tried."""
    if not refused:
        return False
    for digest in {hashlib.sha256(payload).hexdigest(), hashlib.sha256(encode(msg)).hexdigest()}:
        if refused[key, digest] > 0:
            refused[key, digest] -= 1
            return True
    return False


def rule_named(award: Award) -> str:
    """The settlement rule an award names, with every parameter; one of schemas before version 3 names none,
    which is the paper's at the award's rates."""
    return award.settlement_rule or paper_rule(award.penalty_per_mwh, award.credit_per_mwh).label


def recorded_rule(day: RecordedDay, trust: Trust | None = None) -> ChosenRule:
    """The rule the day was settled by, as its awards name it. A built-in is made again from its name; a rule of
    one's own is loaded again from where it was named only if ``trust`` allows it (by default it does not:
    UntrustedRule, before anything is imported); ResettleError if it cannot be loaded."""
    spec = rule_named(day.terms)
    try:
        return (trust or Trust()).choose(spec)
    except UntrustedRule:
        raise
    except ValueError as err:
        raise ResettleError(f"{day.market_day} was settled by {spec}, which cannot be used here: {err}") from None


def resettle(day: RecordedDay, rule: ChosenRule | None = None) -> dict[str, Statement]:
    """Every agent's statement from the recorded awards and meter reports, under the recorded rule (a built-in; see
    ``recorded_rule`` for one of the recording's own) unless ``rule`` says otherwise. The agents' recorded behaviour
    is held fixed: their readings are what they were."""
    prices, own = day.prices()
    settled = accepted_day({a: aw.p_sch_mw for a, aw in day.awards.items()}, prices, day.meter,
                           subperiods=day.terms.subperiods, registered=day.registered, agent_prices=own,
                           grid=day.grid, bus={a: aw.bus for a, aw in day.awards.items() if aw.bus is not None})
    statements, _ = (rule or recorded_rule(day)).settle(settled)
    return statements


def as_message(day: RecordedDay, st: Statement) -> SettlementStatement:
    """A statement under the recorded rule, as the DMO would have sent it."""
    terms = day.terms
    return statement_message(st, day.market_day, terms.penalty_per_mwh, terms.credit_per_mwh, terms.settlement_rule)


def compare(day: RecordedDay, statements: dict[str, Statement]) -> list[str]:
    """Every difference between the recomputed and the recorded statements (and the day summary's totals):
    per agent, each statement field and each field of each hour's line. Empty when identical."""
    diffs = []
    for agent in sorted(set(statements) | set(day.statements)):
        if agent not in day.statements:
            diffs.append(f"{agent}: no statement recorded")
            continue
        if agent not in statements:
            diffs.append(f"{agent}: a statement was recorded, but the agent has no recorded award")
            continue
        new, old = as_message(day, statements[agent]), day.statements[agent]
        for name in STATEMENT_FIELDS:
            if getattr(new, name) != getattr(old, name):
                diffs.append(f"{agent} {name}: recorded {getattr(old, name)!r}, recomputed {getattr(new, name)!r}")
        for new_line, old_line in zip(new.lines, old.lines):
            a, b = new_line.model_dump(), old_line.model_dump()
            for name in a:
                if a[name] != b[name]:
                    diffs.append(f"{agent} hour {old_line.hour} {name}: recorded {b[name]!r}, recomputed {a[name]!r}")
    if day.summary_totals is not None:
        for agent in sorted(statements):
            recorded = day.summary_totals.get(agent)
            if recorded is None:
                diffs.append(f"{agent}: missing from the day summary's totals")
                continue
            st = as_message(day, statements[agent])
            for name in ("energy_charge", "deviation_penalty", "deviation_credit", "total"):
                if recorded[name] != getattr(st, name):
                    diffs.append(f"{agent} day summary {name}: recorded {recorded[name]!r}, "
                                 f"recomputed {getattr(st, name)!r}")
    return diffs


def resettled_differences(rec: Recording, days: list[str], trust: Trust | None = None) -> list[str]:
    """Each of ``days`` (market days) re-settled from the recording alone under the rule it names
    (``recorded_rule``, with ``trust``), against the statements it records: the differences (``compare``), each
    after its market day; empty when every statement re-settles to the cent. ResettleError when a day cannot be
    re-settled, UntrustedRule as ``recorded_rule``."""
    out = []
    for name in days:
        day = recorded_day(rec, name)
        out += [f"{name}: {d}" for d in compare(day, resettle(day, recorded_rule(day, trust)))]
    return out
