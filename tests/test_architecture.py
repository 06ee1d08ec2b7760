"""The package's import graph: one-way layers and no cycles, counting imports inside functions too.

configs, meshes (data) -> physics -> experiments (the paper's) -> envs -> agents -> benchmarks -> cli (the command
line). An import inside a function hides a cycle from Python at import time but not from a reader; this test reads
them all.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("configs", "meshes", "physics", "experiments", "envs", "agents", "benchmarks", "cli")  # a module may import only its own layer and lower ones


def _modules() -> dict[str, Path]:
    mods = {"msdgrasp": ROOT / "__init__.py"}
    for layer in LAYERS:
        for path in (ROOT / layer).rglob("*.py"):  # (subpackages too: agents/learners)
            parts = path.relative_to(ROOT).with_suffix("").parts
            mods["msdgrasp." + ".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return mods


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (anywhere in its source)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                continue
            graph[name] |= {t for t in targets if t in mods and t != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_planted_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    assert _cycles(import_graph()) == []


def test_layers_import_only_downward():
    rank = {layer: k for k, layer in enumerate(LAYERS)}
    upward = []
    for name, targets in import_graph().items():
        if name == "msdgrasp":
            continue  # the package root registers the envs
        own = rank[name.split(".")[1]]
        for target in targets:
            if target != "msdgrasp" and rank[target.split(".")[1]] > own:
                upward.append(f"{name} -> {target}")
    assert upward == []


def test_the_graph_sees_imports_inside_functions():
    graph = import_graph()
    # cli.rl imports its handlers' modules lazily (inside functions) to keep --help fast
    assert "msdgrasp.agents.seeds" in graph["msdgrasp.cli.rl"]
    assert "msdgrasp.physics.integrator" in graph["msdgrasp.physics.simulation"]


def test_the_wheel_lists_every_subpackage():
    """setuptools installs the packages pyproject.toml names, no others: a folder with an ``__init__.py`` missing
    there is missing from every non-editable install."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(("msdgrasp",) + p.parent.relative_to(ROOT).parts)
             for layer in LAYERS for p in (ROOT / layer).rglob("__init__.py")} | {"msdgrasp"}
    assert listed == found
