"""The package's import graph has no cycles: every module of src/tissuecast imports, and
layers only import downward (:data:`LAYERS`, read the way the pipeline runs).

The graph is read from the source with ``ast`` (module-level, function-level and
``TYPE_CHECKING`` imports alike: a cycle through an annotation-only import is still two
modules that each need the other to be understood).
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import tissuecast

PACKAGE_ROOT = Path(tissuecast.__file__).parent

#: Cycles left to close, each through one annotation-only (``TYPE_CHECKING``) import; remove an
#: entry when its cycle is gone (the test then fails if it comes back).
KNOWN_TYPE_ONLY_CYCLES = {
    frozenset({"tissuecast.fem.newton", "tissuecast.fem.solver"}),  # SolveRun's annotation of its Solver
}


def module_names() -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is package) for every module of the package."""
    out = {}
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return out


def _absolute(module: str, is_package: bool, node: ast.ImportFrom) -> str | None:
    if not node.level:
        return node.module
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph(modules: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """Module -> the package modules it imports (``from pkg import sub`` counts as ``pkg.sub``)."""
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, is_package) in modules.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                target = _absolute(name, is_package, node)
                if not target:
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    hit = sub if sub in modules else target
                    if hit in modules:
                        graph[name].add(hit)
            elif isinstance(node, ast.Import):
                graph[name].update(a.name for a in node.names if a.name in modules)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(frozenset(component))
    return found


def test_cycle_finder_finds_a_cycle_and_nothing_else():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [frozenset({"a", "b", "c"})]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_relative_imports_resolve_to_package_modules():
    modules = module_names()
    graph = import_graph(modules)
    assert "tissuecast.surrogate.weights" in graph["tissuecast.surrogate.network"]
    assert "tissuecast.config" in graph["tissuecast.surrogate.model"]
    assert "tissuecast.errors" in graph["tissuecast.config"]


def test_no_import_cycles():
    found = set(cycles(import_graph(module_names())))
    new = found - KNOWN_TYPE_ONLY_CYCLES
    assert not new, "import cycles: " + "; ".join(" <-> ".join(sorted(c)) for c in new)
    assert found == KNOWN_TYPE_ONLY_CYCLES, "a known cycle is gone: remove it from KNOWN_TYPE_ONLY_CYCLES"


@pytest.mark.parametrize("name", sorted(module_names()))
def test_every_module_imports(name):
    importlib.import_module(name)


#: The packages of src/tissuecast by layer, bottom first: a package imports only from its own
#: layer or below. ``root`` is tissuecast/__init__.py (its version is read anywhere).
LAYERS = (
    ("errors", "frames", "registration", "instruments", "root"),
    ("config",),
    ("mesh", "forces", "slicer"),
    ("fem",),
    ("scenario", "markers"),
    ("dataset",),
    ("surrogate", "planning", "inverse"),
    ("evaluate", "serve"),
    ("app",),
    ("cli",),
)
#: Upward imports left to close, with their reason (none: config's checks that need the mesh
#: package moved to the edge, issue 30 part 3).
KNOWN_UPWARD: dict = {}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "root"


def test_layers_only_import_downward():
    layer = {pkg: k for k, group in enumerate(LAYERS) for pkg in group}
    modules = module_names()
    assert {_package(m) for m in modules} <= set(layer), "a package is in no layer: add it to LAYERS"
    upward = set()
    for a, targets in import_graph(modules).items():
        for b in targets:
            pa, pb = _package(a), _package(b)
            if pa != pb and layer[pb] > layer[pa] and pb != "root":
                upward.add((pa, pb))
    new = upward - set(KNOWN_UPWARD)
    assert not new, "upward imports: " + ", ".join(f"{a} -> {b}" for a, b in sorted(new))
    assert upward == set(KNOWN_UPWARD), "an upward import is gone: remove it from KNOWN_UPWARD"
