"""``dmosim settle PATH...``: re-settle recorded days and compare with their recorded statements, or under other rules.

Each PATH is a recording, a run directory (its ``recording.mcap``) or a sweep directory (every run in it). Every
market day a recording reaches is settled (``--day`` picks one). Without a rule: exit 0 when every recomputed
statement equals the recorded one, field by field and line by line; 1 with the list of differences. With
``--rule`` (repeatable), or ``--penalty`` / ``--credit`` (the recorded paper rule at other rates), the days are
re-settled under each rule, the agents' recorded behaviour held fixed, and one table compares them (exit 0).

A recorded rule of the recording's own (not built in) is loaded only if ``--rule`` names the same code, or with
``--trust-rules``; otherwise settling by it is refused in one line (docs/settlement.md, "Rules named by recordings").
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from dmo.market.choice import ChosenRule, Trust, UntrustedRule, choose, paper_rule
from dmo.replay.resettle import (RecordedDay, ResettleError, compare, gaps, held_days, recorded_day, recorded_rule,
                                 recording_days, resettle)

from ..arguments import market_day, nonneg_float
from ..console import UsageError, print_json
from ..experiment.rundir import RunDir
from ..results.order import natural
from .flags import add_trust_flag, load_recording, recorded_day_flag, untrusted

HELP = "re-settle the market days of recordings, run directories or sweep directories: compare with the recorded statements, or under other settlement rules"
FIXED = ("re-settled with the agents' recorded behaviour held fixed: their metered imports are what they were under "
         "the recorded rule; to see how agents respond to a rule, run the experiment under it")
COLUMNS = ("recording", "agent", "rule", "energy_charge", "deviation_penalty", "deviation_credit", "total",
           "recorded_total", "change")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", nargs="+", help="each a recording, a run directory or a sweep directory (every run in it)")
    p.add_argument("--rule", action="append", default=[], metavar="RULE",
                   help="re-settle under this rule (repeatable): a built-in, NAME[:key=value,...] (paper, symmetric, "
                        "deadband, price-linked; docs/settlement.md), or path/to/rules.py:function[:key=value,...]")
    p.add_argument("--penalty", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under the recorded paper rule at this penalty rate ($/MWh)")
    p.add_argument("--credit", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under the recorded paper rule at this under-import credit rate ($/MWh)")
    p.add_argument("--day", type=market_day, metavar="YYYY-MM-DD",
                   help="settle only this market day of a recording of several (default: every day recorded)")
    p.add_argument("--csv", metavar="FILE", help="also write the comparison of rules to this CSV file")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    add_trust_flag(p)


def run(args) -> int:
    paths = recordings(args.path)
    try:
        rules = [choose(spec) for spec in args.rule]
    except ValueError as err:
        raise UsageError(f"--rule: {err}") from None
    if args.csv and not (rules or args.penalty is not None or args.credit is not None):
        raise UsageError("--csv writes the comparison of rules: give --rule, --penalty or --credit")
    trust = Trust.of(args.trust_rules, args.rule)  # a rule of its own a recording names: only one named here
    if rules or args.penalty is not None or args.credit is not None:
        return _compare_rules(args, paths, rules, trust)
    outcomes = [_verify(args, load_recording(str(path)), trust) for path in paths]
    if args.json:
        print_json(outcomes[0] if len(outcomes) == 1 else {"recordings": outcomes})
    return 1 if any(not o["identical"] for o in outcomes) else 0


def recordings(paths: list[str]) -> list[Path]:
    """The recordings PATHs name: a file as it is, a run directory's recording, every run of a sweep directory."""
    out = []
    for given in paths:
        path = Path(given)
        if path.is_dir():
            found = [RunDir(path).recording] if RunDir(path).recording.is_file() else sorted(
                RunDir(run).recording for run in path.iterdir() if RunDir(run).recording.is_file())
            if not found:
                raise UsageError(f"{given}: a directory with no recording, nor run directories holding one")
            out += found
        else:
            out.append(path)
    return out


def _verify(args, rec, trust: Trust) -> dict:
    """Re-settle one recording's days under the recorded rule and compare with its statements; print the outcome
    unless ``--json``."""
    days = _days(rec, args.day)
    if not any(day.statements for day in days):
        raise UsageError(f"{rec.path}: no settlement statements recorded to compare with"
                         + (f" ({rec.cut_note})" if rec.cut_note else ""))
    if rec.cut_note:
        print(f"warning: {rec.path}: {rec.cut_note}; settling what was recorded before the cut", file=sys.stderr)
        if not days[-1].statements:
            print(f"warning: {rec.path}: {days.pop().market_day} is not settled in the recording; left out",
                  file=sys.stderr)
    results = [_settled(rec, day, trust) for day in days]
    diffs = [d for r in results for d in r["differences"]]
    lacking = gaps(rec) if diffs else []
    lines = sum(r["lines"] for r in results)
    left_out = sum(r["meter_reports_left_out"] for r in results)
    totals = {a: round(sum(r["totals"].get(a, 0.0) for r in results), 2) for a in sorted(results[-1]["totals"], key=natural)}
    if args.json:
        return {"path": rec.path, "complete": rec.complete, "identical": not diffs, "agents": list(totals),
                "market_days": [r["market_day"] for r in results], "lines": lines,
                "meter_reports_left_out": left_out, "differences": diffs, "recording_lacks": lacking,
                "totals": totals, "days": results}
    if diffs:
        print(f"{rec.path}: {len(diffs)} difference(s) between the recorded and the recomputed statements:")
        for d in diffs:
            print(f"  {d}")
        for gap in lacking:
            print(f"  the recording lacks: {gap}")
    else:
        of = f"{len(results)} market days, " if len(results) > 1 else ""
        print(f"{rec.path}: {of}{sum(len(r['totals']) for r in results)} statements ({lines} hour lines) re-settled "
              f"from the recorded awards and meter reports: identical to the recorded ones"
              + (f" ({left_out} refused meter reports left out)" if left_out else ""))
    return {"identical": not diffs}


def _days(rec, wanted: str | None) -> list[RecordedDay]:
    """The recorded days to settle: ``wanted`` (a market day), else every day the recording reaches."""
    days = [recorded_day_flag(rec, wanted)] if wanted else held_days(rec) or recording_days(rec)[:1]
    try:
        out = [recorded_day(rec, day) for day in days or [None]]
    except (ResettleError, ValueError) as exc:
        reason = str(exc) if isinstance(exc, ResettleError) else f"{rec.path}: cannot re-settle: {exc}"
        lacking = gaps(rec)
        raise UsageError(reason + (f"; the recording lacks: {'; '.join(lacking)}" if lacking else "")) from None
    return out


def _recorded_rule(rec, day: RecordedDay, trust: Trust) -> ChosenRule:
    """The rule ``day`` was settled by, or the one line of a rule the recording names that ``trust`` keeps from
    running, or that cannot be loaded."""
    try:
        return recorded_rule(day, trust)
    except UntrustedRule as err:
        raise untrusted(f"{rec.path}: {day.market_day} was settled by {err.spec}", err.spec, "--rule") from None
    except ResettleError as err:
        raise UsageError(f"{rec.path}: {err}") from None


def _settled(rec, day: RecordedDay, trust: Trust) -> dict:
    """One day re-settled and compared with its recorded statements; differences start with the market day when
    the recording is of several."""
    rule = _recorded_rule(rec, day, trust)
    try:
        statements = resettle(day, rule)
    except ValueError as err:  # a rule that fails on this day: one line naming it
        raise UsageError(f"{rec.path}, {day.market_day}: {err}") from None
    several = len(recording_days(rec)) > 1
    diffs = [f"{day.market_day}: {d}" if several else d for d in compare(day, statements)]
    return {"market_day": day.market_day, "identical": not diffs, "differences": diffs,
            "lines": sum(len(st.lines) for st in statements.values()), "meter_reports_left_out": day.left_out,
            "totals": {a: float(st.total) for a, st in statements.items()}}


def _compare_rules(args, paths: list[Path], rules: list[ChosenRule], trust: Trust) -> int:
    """Each agent's bill over the chosen days of each recording, under each rule, against its recorded bill."""
    rows = []
    for path in paths:
        rec = load_recording(str(path))
        days = [day for day in _days(rec, args.day) if day.statements or not rec.cut_note]
        name = str(path.parent if path == RunDir(path.parent).recording else path)
        for rule in _rules_of(args, days, rules):
            sums: dict[str, dict[str, float]] = {}
            for day, chosen in zip(days, rule):
                try:
                    statements = resettle(day, chosen)
                except ValueError as err:
                    raise UsageError(f"{rec.path}, {day.market_day}: {err}") from None
                for agent, st in statements.items():
                    row = sums.setdefault(agent, dict.fromkeys(COLUMNS[3:8], 0.0))
                    old = day.statements.get(agent)  # recorded, else as the recorded rule gives it
                    row["recorded_total"] += old.total if old is not None else float(
                        resettle(day, _recorded_rule(rec, day, trust))[agent].total)
                    for column, value in (("energy_charge", st.energy_charge), ("deviation_penalty",
                                          st.deviation_penalty), ("deviation_credit", st.credit), ("total", st.total)):
                        row[column] += float(value)
            for agent, row in sorted(sums.items(), key=lambda item: natural(item[0])):
                rows.append({"recording": name, "agent": agent, "rule": rule[0].label,
                             **{k: round(v, 2) for k, v in row.items()},
                             "change": round(row["total"] - row["recorded_total"], 2)})
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
    if args.json:
        print_json({"recordings": [str(p) for p in paths], "note": FIXED, "rows": rows})
        return 0
    print(f"{FIXED}.")
    widths = {c: max(len(c), *(len(_cell(r[c])) for r in rows)) for c in COLUMNS}
    print("  ".join(c.ljust(widths[c]) if c in COLUMNS[:3] else c.rjust(widths[c]) for c in COLUMNS))
    for r in rows:
        print("  ".join(_cell(r[c]).ljust(widths[c]) if c in COLUMNS[:3] else _cell(r[c]).rjust(widths[c])
                        for c in COLUMNS))
    if args.csv:
        print(f"wrote {args.csv}")
    return 0


def _rules_of(args, days: list[RecordedDay], rules: list[ChosenRule]) -> list[list[ChosenRule]]:
    """Per rule to compare, the rule of each day: ``--rule`` as given; ``--penalty`` / ``--credit`` as the paper rule
    at the rates the flags give, each day's awarded rate for the one left out."""
    out = [[rule] * len(days) for rule in rules]
    if args.penalty is not None or args.credit is not None:
        out.append([paper_rule(day.terms.penalty_per_mwh if args.penalty is None else args.penalty,
                               day.terms.credit_per_mwh if args.credit is None else args.credit) for day in days])
    return out


def _cell(value) -> str:
    return f"{value:,.2f}" if isinstance(value, float) else str(value)
