"""``dmosim bench NAME``: run one benchmark and print its figures as a table or one JSON object."""

from __future__ import annotations

import importlib

from ..console import print_json


def run(args) -> int:
    result = importlib.import_module(args.bench_module).run(args)
    if args.json:
        print_json(result)
    else:
        print(render(result))
    return 0


def render(result: dict, indent: str = "") -> str:
    """Nested dicts as indented sections; lists of dicts (rows) as aligned tables."""
    lines = []
    for key, value in result.items():
        if isinstance(value, dict):
            lines += [f"{indent}{key}:", render(value, indent + "  ")]
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            cols = list(value[0])
            cells = [[_cell(row.get(c)) for c in cols] for row in value]
            widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(cols)]
            lines.append(f"{indent}{key}:")
            lines.append(indent + "  " + "  ".join(c.rjust(w) for c, w in zip(cols, widths)))
            lines += [indent + "  " + "  ".join(x.rjust(w) for x, w in zip(r, widths)) for r in cells]
        else:
            lines.append(f"{indent}{key}: {_cell(value)}")
    return "\n".join(lines)


def _cell(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if abs(value) < 1e4 else f"{value:,.0f}"
    return str(value)
