"""What every command shares at the terminal: the user-input error, progress lines, JSON output."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit 2."""


SIBLINGS = ("scenarios", "messages", "microgrid_agent", "dmo")  # the packages installed beside dmosim
_HOME = Path(__file__).resolve().parents[1]  # where they are: the directory that holds dmosim/


def shadowing(packages: tuple[str, ...] = SIBLINGS, home: Path = _HOME) -> str | None:
    """The one line saying which file Python would import instead of one of our ``packages``, else None.

    ``python -m`` and scripts put the current directory first on ``sys.path``, so a user's own ``scenarios.py``
    (or ``messages/``) there is found before the package installed beside dmosim, and an import of ours fails far
    away from the cause. Found without importing (``find_spec`` of a top-level name runs nothing)."""
    for name in packages:
        module = sys.modules.get(name)
        spec = module.__spec__ if module is not None else importlib.util.find_spec(name)
        if spec is None:
            continue  # not installed at all: the import itself says so
        found = spec.origin or next(iter(spec.submodule_search_locations or ()), None)
        if found is None or Path(found).resolve() != (home / name / "__init__.py").resolve():
            return (f"{found or name} shadows dmosim's package {name!r} (Python finds it first on sys.path: the "
                    "current directory, with python -m, or PYTHONPATH); rename it, or run the installed dmosim "
                    "command from another directory (README.md)")
    return None


def refuse_shadowed_packages() -> None:
    """Exit 2 with ``shadowing``'s line, before anything of ours imports the wrong package."""
    why = shadowing()
    if why is not None:
        print(f"error: {why}", file=sys.stderr)
        raise SystemExit(2)


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
