"""There is always a scenario: no source of the package asks whether there is one.

The paper's set-up (pins and LBO nodal forces) is the default scenario, not a path of its
own. Where behaviour differs by physics it is decided by a property of the scenario (e.g.
``Scenario.hangs_on_pins``, ``Scenario.can_swing``), never by ``scenario is None``, a
``uses_scenario``-style predicate, or an optional ``scenario=None`` argument. The sources are
read with ``ast`` and regular expressions, like ``test_import_graph.py``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import tissuecast

PACKAGE_ROOT = Path(tissuecast.__file__).parent

#: "Is there a scenario" written out: a comparison of something named ``scenario`` (or
#: ``*.scenario``, ``*_scenario``) with None, or the old path predicate.
BRANCH = re.compile(r"\b\w*scenario\s+is\s+(?:not\s+)?None\b|\buses_scenario\b")


def optional_scenario_arguments(source: str) -> list[str]:
    """``function(argument)`` of every parameter named ``scenario`` (or ending in ``_scenario``)
    whose default is None."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        args = node.args
        positional = args.posonlyargs + args.args
        pairs = list(zip(positional[len(positional) - len(args.defaults):], args.defaults))
        pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
        for arg, default in pairs:
            named = arg.arg == "scenario" or arg.arg.endswith("_scenario")
            if named and isinstance(default, ast.Constant) and default.value is None:
                found.append(f"{node.name}({arg.arg})")
    return found


def scenario_branches(source: str) -> list[str]:
    """The "is there a scenario" branches in ``source``: lines matching :data:`BRANCH` and
    optional scenario arguments."""
    lines = [f"line {k}: {line.strip()}" for k, line in enumerate(source.splitlines(), 1) if BRANCH.search(line)]
    return lines + optional_scenario_arguments(source)


def test_the_finder_sees_each_kind_of_branch():
    assert scenario_branches("if self.scenario is None:\n    pass\n")
    assert scenario_branches("x = 1 if recipe.scenario is not None else 2\n")
    assert scenario_branches("if uses_scenario(cfg):\n    pass\n")
    assert scenario_branches("def f(mesh, scenario=None):\n    return mesh\n") == ["f(scenario)"]
    assert scenario_branches("def f(mesh, *, deck_scenario=None):\n    return mesh\n") == ["f(deck_scenario)"]
    assert not scenario_branches("def f(scenario, draw=None):\n    return scenario.sample(draw)\n")
    assert not scenario_branches("if draw.body_force is None:\n    pass\n")


def test_no_source_asks_whether_there_is_a_scenario():
    found = {}
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        hits = scenario_branches(path.read_text(encoding="utf-8"))
        if hits:
            found[str(path.relative_to(PACKAGE_ROOT))] = hits
    assert not found, f"'is there a scenario' branches (the paper's set-up is a scenario): {found}"
