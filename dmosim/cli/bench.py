"""``dmosim bench NAME``: run one benchmark and print its figures as a table or one JSON object."""

from __future__ import annotations

import argparse

from ..console import print_json

HELP = "benchmarks that print ratios and absolute times measured side by side (docs/benchmarks.md)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """One sub-command per benchmark module of dmosim/bench/, its flags its own."""
    from ..bench import (  # noqa: PLC0415  (solver: the solver stack)
        clearing, day, fleet, flood, messaging, recording, recovery, solver, start, week)

    sub = p.add_subparsers(dest="bench", required=True, parser_class=type(p))
    for module in (day, week, fleet, messaging, recording, recovery, flood, solver, start, clearing):
        bench = sub.add_parser(module.__name__.rsplit(".", 1)[1], help=module.__doc__.splitlines()[0])
        module.add_arguments(bench)
        bench.add_argument("--json", action="store_true", help="print one JSON object")
        bench.set_defaults(bench_run=module.run)


def run(args) -> int:
    result = args.bench_run(args)
    if args.json:
        print_json(result)
    else:
        print(render(result))
    return 0


def render(result: dict, indent: str = "") -> str:
    """Nested dicts as indented sections; lists of dicts (rows) as aligned tables."""
    lines = []
    for key, value in result.items():
        if isinstance(value, dict) and value:
            lines += [f"{indent}{key}:", render(value, indent + "  ")]
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            cols = list(dict.fromkeys(c for row in value for c in row))  # a row may lack a column: "-"
            cells = [[_cell(row.get(c)) for c in cols] for row in value]
            widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(cols)]
            lines.append(f"{indent}{key}:")
            lines.append(indent + "  " + "  ".join(c.rjust(w) for c, w in zip(cols, widths)))
            lines += [indent + "  " + "  ".join(x.rjust(w) for x, w in zip(r, widths)) for r in cells]
        else:
            lines.append(f"{indent}{key}: {_cell(value)}")
    return "\n".join(lines)


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e4 else f"{value:,.0f}"
    return str(value)
