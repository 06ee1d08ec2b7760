"""The package's import graph: one-way layers and no cycles, counting imports inside functions too; and the core
install: the envs work without any optional dependency.

configs, meshes (data) -> physics -> experiments (the paper's) -> envs -> agents -> benchmarks -> cli (the command
line). An import inside a function hides a cycle from Python at import time but not from a reader; this test reads
them all.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# a module may import only its own layer and lower ones
LAYERS = ("configs", "meshes", "physics", "experiments", "envs", "agents", "benchmarks", "cli")


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


#: the optional dependencies (pyproject.toml's extras), top-level module names
OPTIONAL = ("torch", "stable_baselines3", "rerun", "tensorboard", "matplotlib", "tqdm", "imageio", "imageio_ffmpeg",
            "rsl_rl", "tensordict", "ray", "minari", "mujoco", "gmsh", "skfem")

CORE_ONLY = textwrap.dedent("""
    import importlib.abc
    import json
    import sys

    BLOCKED = set(sys.argv[1].split(","))
    tried = []


    class NotInstalled(importlib.abc.MetaPathFinder):
        # every optional dependency imports as on a core install: ModuleNotFoundError
        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                tried.append(name)
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None


    sys.meta_path.insert(0, NotInstalled())
    import gymnasium as gym

    import msdgrasp.envs  # noqa: F401

    out = {"steps": {}}
    for env_id in ("msdgrasp/GraspLift-v0", "msdgrasp/GraspLiftSphere-v0", "msdgrasp/GraspLift-v1",
                   "msdgrasp/GraspLiftSphere-v1"):
        env = gym.make(env_id)
        obs, _ = env.reset(seed=0)
        obs2, reward, terminated, truncated, info = env.step(env.action_space.sample())
        out["steps"][env_id] = [len(obs), len(obs2), float(reward), bool(terminated or truncated)]
        env.close()
    out["tried"] = sorted(tried)
    errors = []
    for attempt in (lambda: gym.make("msdgrasp/GraspLift-v0", render_mode="rgb_array"),
                    lambda: __import__("msdgrasp.envs.sb3"), lambda: __import__("msdgrasp.agents.networks")):
        try:
            attempt()
            errors.append(None)
        except ImportError as exc:
            errors.append([type(exc).__name__, str(exc)])
    out["errors"] = errors
    print(json.dumps(out))
""")


def test_the_envs_run_on_the_core_install_and_a_missing_extra_is_one_line_naming_it():
    """With every optional dependency missing (a fresh interpreter where importing one fails), ``import
    msdgrasp.envs``, ``gym.make`` of both ids, reset and a step work and never try to import one; what does need
    one (rendering, the SB3 adapter and policies) stops with a one-line ImportError naming the extra."""
    proc = subprocess.run([sys.executable, "-c", CORE_ONLY, ",".join(OPTIONAL)], capture_output=True, text=True,
                          env=os.environ.copy(), timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert sorted(out["steps"]) == ["msdgrasp/GraspLift-v0", "msdgrasp/GraspLift-v1", "msdgrasp/GraspLiftSphere-v0",
                                    "msdgrasp/GraspLiftSphere-v1"]
    for n_obs, n_obs2, reward, _ in out["steps"].values():
        assert n_obs == n_obs2 > 0 and reward == reward  # (not NaN)
    assert out["tried"] == []
    render, sb3, networks = out["errors"]
    assert render == ["MissingExtraError", "GraspLiftEnv: render_mode='rgb_array': matplotlib is not installed; "
                                           "pip install 'msdgrasp[viz]'"]
    assert sb3 == ["MissingExtraError", "the Stable-Baselines3 adapter: stable_baselines3 is not installed; "
                                        "pip install 'msdgrasp[train]'"]
    assert networks[0] == "MissingExtraError" and networks[1].endswith("pip install 'msdgrasp[train]'")
