"""``dmosim plot PATH``: recorded market days as one PNG: clearing prices and congestion, each agent's award
against its metered import with islanded hours shaded, its deviation penalty and credit per hour, and its daily
totals (dmosim/results/figures.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..console import UsageError
from .flags import RECORDING_HELP, load_recording

HELP = "the market days of a recording or a run directory as one PNG: prices, awards against metered imports, penalties and credits, totals"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help=RECORDING_HELP)
    p.add_argument("--out", metavar="FILE",
                   help="the PNG to write (default: a run directory's run.png, else <recording stem>.png beside "
                        "the recording)")


def default_figure(path: Path) -> Path:
    """Where the figure goes without ``--out``: a run directory's ``run.png``, else beside the recording."""
    from ..experiment.rundir import RunDir  # noqa: PLC0415

    return RunDir(path).figure if path.is_dir() else path.with_suffix(".png")


def run(args) -> int:
    out = Path(args.out) if args.out else default_figure(Path(args.path))
    if out.is_dir():
        raise UsageError(f"{out} is a directory; give a file name, e.g. {out / 'day.png'}")
    if not out.parent.is_dir():
        raise UsageError(f"cannot write {out}: directory {out.parent} does not exist")
    rec = load_recording(args.path)
    from dmosim.studies.figures import save  # noqa: PLC0415  (matplotlib: only for the verb that needs it)

    from ..results.figures import figure_of  # noqa: PLC0415
    from ..results.tables import tables  # noqa: PLC0415

    frames = tables(rec)
    if frames["hours"].empty:
        raise UsageError(f"{rec.path}: no settlement statement recorded, nothing to plot"
                         + (f" ({rec.cut_note})" if rec.cut_note else ""))
    save(figure_of(rec, frames, f"{Path(rec.path).name}: run {rec.run_id or '?'}"), out)
    print(out)
    return 0
