"""Every library the packages import is declared in pyproject.toml: a dependency, or an optional one for the verbs
that need it, so that `pip install .` brings what the code imports and nothing works only by another's luck."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OURS = ("scenarios", "messages", "microgrid_agent", "dmo", "dmosim")


def normal(name: str) -> str:
    """A distribution's name as PEP 503 compares them."""
    return re.sub(r"[-_.]+", "-", name).lower()


def imported() -> dict[str, set[str]]:
    """Each top-level module outside the standard library and our packages, with the files that import it."""
    found: dict[str, set[str]] = {}
    for package in OURS:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for top in {name.split(".")[0] for name in names} - set(OURS) - sys.stdlib_module_names:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = project["dependencies"] + [r for extra in project["optional-dependencies"].values() for r in extra]
    return {normal(re.match(r"[A-Za-z0-9_.-]+", r).group()) for r in requirements}


def test_every_imported_library_is_declared():
    distributions = packages_distributions()
    undeclared = {top: sorted(files) for top, files in imported().items()
                  if not {normal(d) for d in distributions.get(top, [top])} & declared()}
    assert not undeclared, f"imported but not in pyproject.toml: {undeclared}"
