"""The shape of the code, checked: imports follow the data flow, no private name crosses a module, and every
constant and type has one definition (docs/architecture.md)."""

from __future__ import annotations

import ast
import collections
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("scenarios", "messages", "microgrid_agent", "dmo", "dmosim")
# What each package may import of the others: the flow runs from the case data up to the application.
MAY_IMPORT = {
    "scenarios": set(),
    "messages": {"scenarios"},
    "microgrid_agent": {"scenarios", "messages"},
    "dmo": {"scenarios", "messages", "microgrid_agent"},
    "dmosim": {"scenarios", "messages", "microgrid_agent", "dmo"},
}
SHARED_NAMES = {"HELP"}  # every verb module has its own one-line help


@functools.cache
def modules() -> tuple[tuple[str, Path, ast.Module], ...]:
    """(package, path, syntax tree) of every module, parsed once for all the checks (each only reads the trees)."""
    return tuple((package, path, ast.parse(path.read_text(), str(path)))
                 for package in PACKAGES for path in sorted((ROOT / package).rglob("*.py")))


def dotted(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, tree: ast.Module):
    """(module imported, names taken from it, line) for every import of the file, relative ones resolved."""
    package = dotted(path).split(".") if path.name == "__init__.py" else dotted(path).split(".")[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, (), node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            yield module, tuple(a.name for a in node.names), node.lineno


def test_no_import_runs_up_the_flow():
    wrong = []
    for package, path, tree in modules():
        for module, _, line in imports(path, tree):
            top = module.split(".")[0]
            if top in PACKAGES and top != package and top not in MAY_IMPORT[package]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    assert not wrong, "\n".join(wrong)


def test_no_private_name_is_imported_from_another_module():
    wrong = []
    for _, path, tree in modules():
        for module, names, line in imports(path, tree):
            for name in names:
                if name.startswith("_") and not name.startswith("__"):
                    wrong.append(f"{path.relative_to(ROOT)}:{line} imports {name} from {module}")
    assert not wrong, "\n".join(wrong)


def test_every_module_level_constant_has_one_definition():
    where = collections.defaultdict(list)
    for _, path, tree in modules():
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, ast.AnnAssign) else []
            for target in targets:
                if isinstance(target, ast.Name) and target.id.isupper() and target.id not in SHARED_NAMES:
                    where[target.id].append(str(path.relative_to(ROOT)))
    twice = {name: paths for name, paths in where.items() if len(paths) > 1}
    assert not twice, twice


def test_every_type_name_means_one_thing():
    where = collections.defaultdict(list)
    for _, path, tree in modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                where[node.name].append(str(path.relative_to(ROOT)))
    twice = {name: paths for name, paths in where.items() if len(paths) > 1}
    assert not twice, twice


@pytest.mark.parametrize("package", PACKAGES)
def test_every_module_opens_with_a_sentence_on_its_job(package):
    missing = [str(path.relative_to(ROOT)) for p, path, tree in modules()
               if p == package and path.name != "__main__.py" and not ast.get_docstring(tree)]
    assert not missing, missing


def test_the_checks_see_the_code():
    """The checks above would pass on nothing: make sure they read every package and resolve relative imports."""
    found = {package: 0 for package in PACKAGES}
    resolved = set()
    for package, path, tree in modules():
        found[package] += 1
        resolved.update(module for module, _, _ in imports(path, tree))
    assert all(n >= 5 for n in found.values()), found
    assert {"dmo.market.clearing", "microgrid_agent.model", "messages.keys", "scenarios.horizon"} <= resolved


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of the project it imports, at the top or inside a function alike (a name taken from
    a package is its submodule where one exists)."""
    known = {dotted(path) for _, path, _ in modules()}
    graph = {}
    for _, path, tree in modules():
        edges = set()
        for module, names, _ in imports(path, tree):
            if module.split(".")[0] not in PACKAGES:
                continue
            subs = {f"{module}.{name}" for name in names} & known
            edges |= subs or {module}
        graph[dotted(path)] = edges - {dotted(path)}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_module_imports_a_module_that_imports_it_back():
    assert not cycles(import_graph())


def test_the_cycle_check_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_subpackage_imports_one_that_imports_it_back():
    """One level up from modules: dmosim/bench/ may build on dmosim/cli/ or the other way round, not both; a
    package's own top-level modules (microgrid_agent/instance.py) count one by one."""
    def unit(module: str) -> str:
        return ".".join(module.split(".")[:2])

    graph = collections.defaultdict(set)
    for module, edges in import_graph().items():
        graph[unit(module)] |= {unit(e) for e in edges} - {unit(module)}
    assert not cycles(graph)
