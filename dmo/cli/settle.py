"""``dmosim settle PATH``: re-settle a recorded day and compare with its recorded statements, or with other rates.

Exit 0 when every recomputed statement equals the recorded one, field by field and line by line; 1 with the
list of differences. With ``--penalty`` / ``--credit`` the day is re-settled under those rates instead, and the
change of each agent's bill is printed (exit 0).
"""

from __future__ import annotations

import argparse
import sys

from ..replay.resettle import ResettleError, as_message, compare, gaps, recorded_day, resettle
from .console import UsageError, print_json
from .flags import load_recording, nonneg_float

HELP = "re-settle a recorded day and compare with its recorded statements"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="an MCAP recording")
    p.add_argument("--penalty", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under this penalty rate ($/MWh) and print the change per agent")
    p.add_argument("--credit", type=nonneg_float, default=None, metavar="C",
                   help="re-settle under this under-import credit rate ($/MWh)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args) -> int:
    rec = load_recording(args.path)
    rates = args.penalty is not None or args.credit is not None
    try:
        day = recorded_day(rec)
        statements = resettle(day)
    except (ResettleError, ValueError) as exc:
        reason = str(exc) if isinstance(exc, ResettleError) else f"{rec.path}: cannot re-settle: {exc}"
        lacking = gaps(rec)
        raise UsageError(reason + (f"; the recording lacks: {'; '.join(lacking)}" if lacking else "")) from None
    if not day.statements and not rates:
        raise UsageError(f"{rec.path}: no settlement statements recorded to compare with"
                         + (f" ({rec.cut_note})" if rec.cut_note else ""))
    if rec.cut_note:
        print(f"warning: {rec.path}: {rec.cut_note}; settling what was recorded before the cut", file=sys.stderr)
    if rates:
        return _compare_rates(args, day)
    diffs = compare(day, statements)
    lacking = gaps(rec) if diffs else []
    lines = sum(len(st.lines) for st in statements.values())
    if args.json:
        print_json({"path": rec.path, "complete": rec.complete, "identical": not diffs, "agents": sorted(statements),
                    "lines": lines, "meter_reports_left_out": day.left_out, "differences": diffs,
                    "recording_lacks": lacking, "totals": {a: float(st.total) for a, st in statements.items()}})
    elif diffs:
        print(f"{rec.path}: {len(diffs)} difference(s) between the recorded and the recomputed statements:")
        for d in diffs:
            print(f"  {d}")
        for gap in lacking:
            print(f"  the recording lacks: {gap}")
    else:
        print(f"{rec.path}: {len(statements)} statements ({lines} hour lines) re-settled from the recorded awards "
              f"and meter reports: identical to the recorded ones"
              + (f" ({day.left_out} refused meter reports left out)" if day.left_out else ""))
    return 1 if diffs else 0


def _compare_rates(args, day) -> int:
    terms = day.terms
    penalty = terms.penalty_per_mwh if args.penalty is None else args.penalty
    credit = terms.credit_per_mwh if args.credit is None else args.credit
    base, new = resettle(day), resettle(day, penalty=penalty, credit=credit)
    rows = []
    for agent in sorted(new):
        old = day.statements.get(agent) or as_message(day, base[agent])  # recorded, else as recorded terms give it
        st = as_message(day, new[agent], penalty, credit)
        rows.append({"agent": agent, "total": old.total, "new_total": st.total,
                     "difference": round(st.total - old.total, 2), "deviation_penalty": old.deviation_penalty,
                     "new_deviation_penalty": st.deviation_penalty, "deviation_credit": old.deviation_credit,
                     "new_deviation_credit": st.deviation_credit})
    if args.json:
        print_json({"path": args.path, "penalty_per_mwh": terms.penalty_per_mwh, "credit_per_mwh":
                    terms.credit_per_mwh, "new_penalty_per_mwh": penalty, "new_credit_per_mwh": credit, "agents": rows,
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
