"""`make bench` runs exactly the benchmarks that need no input: a script that requires a data set or
a model would stop the loop at once (it did, until session 44: the first script in the folder
required --dataset)."""

from __future__ import annotations

import ast
import re

from bench_helpers import BENCHMARKS


def standalone_list() -> set[str]:
    text = (BENCHMARKS.parent / "Makefile").read_text()
    block = re.search(r"^STANDALONE_BENCHMARKS :=((?:.*\\\n)*.*)$", text, flags=re.M)
    assert block, "the Makefile names its standalone benchmarks"
    return set(block.group(1).replace("\\\n", " ").split())


def required_arguments(path) -> list[str]:
    """The arguments a script's argparse parser cannot do without: positionals without a default
    or nargs, options marked required, and a required group of alternatives (named "group")."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_mutually_exclusive_group":
            if any(k.arg == "required" and isinstance(k.value, ast.Constant) and k.value.value is True
                   for k in node.keywords):
                out.append("group")
        if not (isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and node.args):
            continue
        first = node.args[0]
        if not (isinstance(first, ast.Constant) and isinstance(first.value, str)):
            continue
        keys = {k.arg: k.value for k in node.keywords}
        if first.value.startswith("-"):
            req = keys.get("required")
            if isinstance(req, ast.Constant) and req.value is True:
                out.append(first.value)
        elif "nargs" not in keys and "default" not in keys:
            out.append(first.value)
    return out


def runnable(path) -> bool:
    return 'if __name__ == "__main__":' in path.read_text()


def test_make_bench_runs_the_benchmarks_that_need_no_input():
    listed = standalone_list()
    scripts = {p.stem: p for p in BENCHMARKS.glob("*.py")}
    assert listed <= set(scripts), f"the Makefile names missing benchmarks: {sorted(listed - set(scripts))}"
    for name, path in scripts.items():
        if not runnable(path):
            assert name not in listed, f"{name} is not a script"
            continue
        need = required_arguments(path)
        assert (name in listed) == (not need), (
            f"benchmarks/{name}.py requires {need}" if need else f"benchmarks/{name}.py runs on its own: list it")


def test_the_parser_reading_sees_required_arguments():
    assert required_arguments(BENCHMARKS / "load_path.py") == ["store"]
    assert "--dataset" in required_arguments(BENCHMARKS / "physics_inverse.py")
    assert required_arguments(BENCHMARKS / "predict_latency.py") == []
    assert required_arguments(BENCHMARKS / "or_robustness.py") == ["group"]
