"""``dmosim export PATH``: a recording's tidy tables (dmosim/results/tables.py) as one CSV or Parquet file each.

The files go to ``--out DIR`` (default: ``<recording stem>-tables`` beside the recording), which is created;
table files already there are replaced. One line per file written. Parquet needs pyarrow, the extra
``dmosim[parquet]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from ..arguments import market_day
from ..console import UsageError
from .flags import RECORDING_HELP, load_recording, recorded_day_flag

HELP = "a recording's or a run directory's tables (hours, days, meter, bids, incidents, rejections) as CSV or Parquet files"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help=RECORDING_HELP)
    p.add_argument("--out", metavar="DIR", help="directory to write the tables to (default: <recording stem>-tables "
                                                "beside the recording)")
    p.add_argument("--day", action="append", type=market_day, metavar="YYYY-MM-DD",
                   help="only this market day's rows (repeatable; default: every day the recording holds)")
    p.add_argument("--format", choices=("csv", "parquet"), default="csv",
                   help="csv (default) or parquet (needs pyarrow: pip install 'dmosim[parquet]')")


def run(args) -> int:
    if args.format == "parquet" and importlib.util.find_spec("pyarrow") is None:
        raise UsageError("--format parquet needs pyarrow, which is not installed: pip install 'dmosim[parquet]'")
    out = Path(args.out) if args.out else Path(args.path).with_name(f"{Path(args.path).stem}-tables")
    rec = load_recording(args.path)
    from ..results.tables import tables, write_tables  # noqa: PLC0415  (pandas: only for the verb that needs it)

    for day in args.day or ():
        recorded_day_flag(rec, day)
    frames = tables(rec)
    if args.day:
        frames = {name: frame[frame["market_day"].isin(args.day)] for name, frame in frames.items()}
    if rec.cut_note:
        print(f"warning: {rec.path}: {rec.cut_note}; exporting what was recorded before the cut", file=sys.stderr)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UsageError(f"cannot write the tables to {out}: not a directory") from None
    except OSError as exc:
        raise UsageError(f"cannot create {out}: {exc.strerror or exc}") from None
    for path, rows in write_tables(frames, out, args.format).items():
        print(f"{path}: {rows} rows")
    return 0
