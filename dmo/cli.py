"""The ``dmosim`` command line: parses flags, runs one command, maps bad input to exit 2 and failures to exit 1."""

from __future__ import annotations

import argparse
import json
import math
import sys

from scenarios.case import CaseError

EXIT_USAGE = 2
EXIT_FAILURE = 1


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse would print the whole usage; one line is enough
        raise UsageError(f"{self.prog}: {message}")


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def hours(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 24:
        raise argparse.ArgumentTypeError(f"expected whole hours 0..24, got {text!r}")
    return value


def nonneg_float(text: str, allow_inf: bool = False) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text!r}") from None
    if math.isnan(value) or value < 0 or (math.isinf(value) and not allow_inf):
        raise argparse.ArgumentTypeError(f"expected a non-negative{' ' if not allow_inf else ' (or inf) '}number, got {text!r}")
    return value


def penalty(text: str) -> float:
    return nonneg_float(text, allow_inf=True)


def gap(text: str) -> float:
    value = nonneg_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a relative gap below 1 (e.g. 0.005), got {text!r}")
    return value


def add_instance_flags(p: argparse.ArgumentParser, scenarios: int) -> None:
    """The flags that define one scheduling instance, shared by ``solve`` and ``study``."""
    p.add_argument("--case", default="paper", help="built-in case name or path to a case TOML file (default: paper)")
    p.add_argument("--scenarios", type=positive_int, default=scenarios, help=f"scenarios after reduction (default: {scenarios})")
    p.add_argument("--sample-size", type=positive_int, default=None, help="scenarios sampled before reduction (default: 10x)")
    p.add_argument("--subperiods", type=positive_int, default=6, help="sub-periods per hour (default: 6, i.e. 10 minutes)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenario draws (default: 0)")
    p.add_argument("--gap", type=gap, default=0.005, help="relative MIP gap to reach (default: 0.005)")
    p.add_argument("--time-limit", type=nonneg_float, default=900.0, help="seconds per solve (default: 900)")
    p.add_argument("--cost-convention", choices=("real", "paper"), default="real",
                   help="real: energy costs x dt; paper: objective (1) as printed, no dt (see docs/model.md)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="dmosim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    solve = sub.add_parser("solve", help="one stochastic day-ahead schedule of one microgrid")
    add_instance_flags(solve, scenarios=10)
    solve.add_argument("--island-hours", type=hours, default=1, help="islanding hours per scenario (default: 1)")
    solve.add_argument("--transfer-scale", type=nonneg_float, default=1.0, help="multiplier of the award P_sch (default: 1)")
    solve.add_argument("--penalty", type=penalty, default=None, help="$/MWh above the award, or inf (default: the case's)")
    solve.add_argument("--metrics", action="store_true", help="also compute VSS and EVPI (solves S + 2 more problems)")
    solve.add_argument("--json", action="store_true", help="print one JSON object (SPEC section 4)")
    solve.add_argument("--verbose", action="store_true", help="show the HiGHS log")
    solve.set_defaults(run="dmo.commands.solve:run")

    from microgrid_agent.studies import STUDIES  # noqa: PLC0415  (the list of studies lives with them)

    study = sub.add_parser("study", help="reproduce the paper's Table II and Figures 2-5")
    study.add_argument("name", choices=sorted(STUDIES), help="which result")
    add_instance_flags(study, scenarios=10)
    study.add_argument("--out", default="out", help="directory for the CSV and PNG files (default: out)")
    study.set_defaults(run="dmo.commands.study:run")
    return parser


def _load(target: str):
    module, _, func = target.partition(":")
    return getattr(__import__(module, fromlist=[func]), func)


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return _load(args.run)(args) or 0
    except (UsageError, CaseError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except RuntimeError as exc:
        print(f"failed: {exc}", file=sys.stderr)
        return EXIT_FAILURE


def print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=2, allow_nan=True)
    sys.stdout.write("\n")


if __name__ == "__main__":
    sys.exit(main())
