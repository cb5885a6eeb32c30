"""``dmosim study NAME``: runs one of the paper's studies with verified solves, writes its CSV and PNG files under
--out, and prints a short table of the results."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenarios.case import load_case

from ..console import UsageError, progress
from ..experiment.rundir import RunDirError, claim_directory
from .solve import add_instance_flags, check_instance_flags, instance_from_args, solve_verified

HELP = "reproduce the paper's Table II and Figures 2-5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from dmosim.studies.paper import STUDIES  # noqa: PLC0415  (pandas: imported for this verb only)

    p.add_argument("name", choices=sorted(STUDIES), help="which result")
    add_instance_flags(p, scenarios=100)  # the paper's "reduced 100 scenarios" (Section IV)
    p.add_argument("--out", default="out", help="directory for the CSV and PNG files (default: out)")


def output_dir(text: str) -> Path:
    """--out as a directory, created if missing; anything else there is a usage error (before any solve)."""
    try:
        return claim_directory(Path(text), overwrite=True)  # a study's files replace the same study's
    except RunDirError as exc:
        raise UsageError(f"--out: {exc}") from None


def run(args) -> int:
    from dmosim.studies import figures, paper, report  # noqa: PLC0415  (pandas, matplotlib)

    check_instance_flags(args)
    out = output_dir(args.out)
    study = paper.STUDIES[args.name]
    units = [u.name for u in load_case(args.case).units]
    progress(f"study {args.name}: {args.scenarios} scenarios x {args.subperiods} sub-periods/h, seed {args.seed}, "
             f"{args.cost_convention} cost convention -> {out}/")
    frames = study(lambda **overrides: instance_from_args(args, **overrides),
                   lambda inst, label: solve_verified(inst, args, label))
    written = [report.write_csv(frame, out / f"{name}.csv") for name, frame in frames.items()]
    fig = report.figure(args.name, frames, args.cost_convention, args.subperiods, units)
    written.append(figures.save(fig, out / f"{args.name}.png"))
    print(report.render(args.name, frames, args.cost_convention, args.subperiods, units))
    print("\nfiles written:")
    for path in written:
        print(f"  {path}")
    return 0
