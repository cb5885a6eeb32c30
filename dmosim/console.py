"""What every command shares at the terminal: the user-input error, progress lines, JSON output."""

from __future__ import annotations

import json
import math
import sys


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit 2."""


def progress(message: str) -> None:
    print(f"dmosim: {message}", file=sys.stderr, flush=True)


def jsonable(obj):
    """JSON has no infinity: an infinite penalty or bound is written as the string "inf"."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return obj


def print_json(obj) -> None:
    json.dump(jsonable(obj), sys.stdout, indent=2)
    sys.stdout.write("\n")
