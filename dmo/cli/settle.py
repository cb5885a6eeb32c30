"""``dmosim settle PATH``: re-settle the recorded days and compare with their recorded statements, or with other rates.

Every market day the recording reaches is settled (``--day`` picks one). Exit 0 when every recomputed statement
equals the recorded one, field by field and line by line; 1 with the list of differences. With ``--penalty`` /
``--credit`` the days are re-settled under those rates instead, and the change of each agent's bill is printed
(exit 0).
"""

from __future__ import annotations

import argparse
import sys

from ..replay.resettle import (RecordedDay, ResettleError, as_message, compare, gaps, held_days, recorded_day,
                               recording_days, resettle)
from .console import UsageError, print_json
from .flags import load_recording, market_day, nonneg_float, recorded_day_flag

HELP = "re-settle recorded market days and compare with their recorded statements"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="an MCAP recording")
    p.add_argument("--penalty", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under this penalty rate ($/MWh) and print the change per agent")
    p.add_argument("--credit", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under this under-import credit rate ($/MWh)")
    p.add_argument("--day", type=market_day, metavar="YYYY-MM-DD",
                   help="settle only this market day of a recording of several (default: every day recorded)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    rec = load_recording(args.path)
    rates = args.penalty is not None or args.credit is not None
    days = _days(rec, args.day)
    if not rates and not any(day.statements for day in days):
        raise UsageError(f"{rec.path}: no settlement statements recorded to compare with"
                         + (f" ({rec.cut_note})" if rec.cut_note else ""))
    if rec.cut_note:
        print(f"warning: {rec.path}: {rec.cut_note}; settling what was recorded before the cut", file=sys.stderr)
    if rates:
        return _compare_rates(args, days)
    if rec.cut_note and not days[-1].statements:
        print(f"warning: {rec.path}: {days.pop().market_day} is not settled in the recording; left out",
              file=sys.stderr)
    results = [_settled(rec, day) for day in days]
    diffs = [d for r in results for d in r["differences"]]
    lacking = gaps(rec) if diffs else []
    lines = sum(r["lines"] for r in results)
    left_out = sum(r["meter_reports_left_out"] for r in results)
    totals = {a: round(sum(r["totals"].get(a, 0.0) for r in results), 2) for a in sorted(results[-1]["totals"])}
    if args.json:
        print_json({"path": rec.path, "complete": rec.complete, "identical": not diffs, "agents": sorted(totals),
                    "market_days": [r["market_day"] for r in results], "lines": lines,
                    "meter_reports_left_out": left_out, "differences": diffs, "recording_lacks": lacking,
                    "totals": totals, "days": results})
    elif diffs:
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
    return 1 if diffs else 0


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


def _settled(rec, day: RecordedDay) -> dict:
    """One day re-settled and compared with its recorded statements; differences start with the market day when
    the recording is of several."""
    statements = resettle(day)
    several = len(recording_days(rec)) > 1
    diffs = [f"{day.market_day}: {d}" if several else d for d in compare(day, statements)]
    return {"market_day": day.market_day, "identical": not diffs, "differences": diffs,
            "lines": sum(len(st.lines) for st in statements.values()), "meter_reports_left_out": day.left_out,
            "totals": {a: float(st.total) for a, st in statements.items()}}


def _compare_rates(args, days: list[RecordedDay]) -> int:
    """Each agent's bill over ``days`` as recorded and under the new rates (each day's recorded rate where a flag
    leaves one unchanged)."""
    terms = days[0].terms
    penalty = terms.penalty_per_mwh if args.penalty is None else args.penalty
    credit = terms.credit_per_mwh if args.credit is None else args.credit
    fields = ("total", "deviation_penalty", "deviation_credit")
    sums: dict[str, dict[str, float]] = {}
    for day in days:
        base, new = resettle(day), resettle(day, penalty=penalty, credit=credit)
        for agent in new:
            old = day.statements.get(agent) or as_message(day, base[agent])  # recorded, else as its terms give it
            st = as_message(day, new[agent], penalty, credit)
            row = sums.setdefault(agent, dict.fromkeys([*fields, *(f"new_{f}" for f in fields)], 0.0))
            for f in fields:
                row[f] += getattr(old, f)
                row[f"new_{f}"] += getattr(st, f)
    rows = [{"agent": agent, **{k: round(v, 2) for k, v in row.items()},
             "difference": round(row["new_total"] - row["total"], 2)} for agent, row in sorted(sums.items())]
    if args.json:
        print_json({"path": args.path, "market_days": [d.market_day for d in days],
                    "penalty_per_mwh": terms.penalty_per_mwh, "credit_per_mwh": terms.credit_per_mwh,
                    "new_penalty_per_mwh": penalty, "new_credit_per_mwh": credit, "agents": rows,
                    "total_difference": round(sum(r["difference"] for r in rows), 2)})
        return 0
    print(f"{args.path}: re-settled at penalty ${penalty:g}/MWh, credit ${credit:g}/MWh "
          f"(recorded: ${terms.penalty_per_mwh:g}/MWh, ${terms.credit_per_mwh:g}/MWh)")
    head = f"{'agent':<10}{'recorded $':>14}{'re-settled $':>14}{'difference $':>14}{'penalty $':>12}{'new penalty $':>15}"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['agent']:<10}{r['total']:>14,.2f}{r['new_total']:>14,.2f}{r['difference']:>+14,.2f}"
              f"{r['deviation_penalty']:>12,.2f}{r['new_deviation_penalty']:>15,.2f}")
    print(f"{'all':<10}{sum(r['total'] for r in rows):>14,.2f}{sum(r['new_total'] for r in rows):>14,.2f}"
          f"{sum(r['difference'] for r in rows):>+14,.2f}")
    return 0
