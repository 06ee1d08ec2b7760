"""Cold compilation: what numba compiles on a first run from an empty cache, and how long each function takes.

A fresh install compiles every kernel on its first call (numba then caches them in ``NUMBA_CACHE_DIR`` or next to
the sources, and later processes load them in about a second). That first call is what a new user, a fresh CI
clone and the first seed of a training pay. This runs a workload in a child process with an empty temporary
``NUMBA_CACHE_DIR``, records numba's compile events and reports, per compiled function, its inclusive time (with the
callees it compiled on the way), its exclusive time and how many signatures were compiled, plus the wall time::

    msdgrasp bench compile [--out logs/bench/compile.json]          (the env workload)
    python -m msdgrasp.benchmarks.compile_time [--what env|float32] [--top 25] [--out logs/bench/compile.json]

``--package NAME`` measures another build of the package on ``sys.path`` instead (a copy under its own name, as
:mod:`.interleaved` takes them), so two builds' compile times can be compared.

``env``: ``GraspLiftEnv()``, reset and one step (what ``gym.make``'s first step compiles: the scene's ``simulate`` in
float64 and the task kernels), timed as a first run is (with its compile helper) and in one process; ``float32``:
one step of a float32 ``Simulation`` of the coarse spleen.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from ..envs.compile_helper import SWITCH

#: the workloads: code run in the child after the recorder is installed (``msdgrasp``: the package measured)
WORKLOADS = {
    "env": ("from msdgrasp.envs.grasp_lift import GraspLiftEnv\n"
            "env = GraspLiftEnv()\nenv.reset(seed=0)\nenv.step(env.action_space.sample())\n"),
    "float32": ("from msdgrasp.physics.mesh_gen import spleen_mesh\n"
                "from msdgrasp.physics.simulation import Simulation\n"
                "from msdgrasp.physics.tissue import TissueModel, TissueParams\n"
                "model = TissueModel.from_params(spleen_mesh('coarse'), TissueParams())\n"
                "Simulation(model, 1, precision='float32').step(1)\n"),
}


def workload(what: str, package: str = "msdgrasp") -> str:
    """The code of workload ``what`` on the build ``package``."""
    return WORKLOADS[what].replace("from msdgrasp.", f"from {package}.")


# Installed in the child before the workload: a listener on numba's compile events that keeps a stack of the
# compilations in progress, so a callee's time is subtracted from its caller's exclusive time.
_RECORDER = """
import json, sys, time
from numba.core import event as _event
_stack, _records = [], {}
class _Listener(_event.Listener):
    def on_start(self, e):
        _stack.append([time.perf_counter(), 0.0])
    def on_end(self, e):
        t0, callees = _stack.pop()
        took = time.perf_counter() - t0
        f = e.data["dispatcher"].py_func
        r = _records.setdefault(f.__module__ + "." + f.__qualname__, [0.0, 0.0, 0])
        r[0] += took
        r[1] += took - callees
        r[2] += 1
        if _stack:
            _stack[-1][1] += took
_event.register("numba:compile", _Listener())
_t0 = time.perf_counter()
"""

_REPORT = """
_wall = time.perf_counter() - _t0
print(json.dumps({"wall_s": _wall, "functions": _records}))
"""


def measure(code: str, timeout_s: float = 1800.0, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run ``code`` in a fresh interpreter with an empty numba cache (and ``env`` added to its environment); its
    compile events, per function ``{"inclusive_s", "exclusive_s", "signatures"}`` sorted by exclusive time, and
    ``wall_s`` (the code's wall time, compilation included). Raises RuntimeError with the child's error if it
    fails."""
    with tempfile.TemporaryDirectory(prefix="msdgrasp-compile-") as cache:
        env = {**os.environ, **(env or {}), "NUMBA_CACHE_DIR": cache}
        proc = subprocess.run([sys.executable, "-c", _RECORDER + code + _REPORT], capture_output=True, text=True,
                              env=env, timeout=timeout_s)
    if proc.returncode != 0:
        raise RuntimeError(f"the workload failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    raw = json.loads(proc.stdout.strip().splitlines()[-1])
    functions = {name: {"inclusive_s": round(inc, 3), "exclusive_s": round(exc, 3), "signatures": n}
                 for name, (inc, exc, n) in sorted(raw["functions"].items(), key=lambda kv: -kv[1][1])}
    return {"wall_s": round(raw["wall_s"], 2),
            "compile_s": round(sum(f["exclusive_s"] for f in functions.values()), 2),
            "functions": functions}


def markdown(report: dict[str, Any], top: int) -> str:
    """The report as a markdown table of the ``top`` functions by exclusive time."""
    head = f"Cold compilation of `{report['what']}`: " if "first_run_wall_s" not in report else (
        f"Cold first run of `{report['what']}`: {report['first_run_wall_s']} s wall (the task's kernels compiled by "
        f"the helper process beside the physics). In one process (`{SWITCH}=0`): ")
    lines = [f"{head}{report['wall_s']} s wall, {report['compile_s']} s compiling ({len(report['functions'])} "
             "functions)", "",
             "| function | exclusive s | inclusive s | signatures |", "|---|---|---|---|"]
    for name, f in list(report["functions"].items())[:top]:
        lines.append(f"| {name} | {f['exclusive_s']} | {f['inclusive_s']} | {f['signatures']} |")
    return "\n".join(lines) + "\n"


def _report(what: str, package: str, top: int, out: Path | None) -> int:
    """Measure, print the JSON to stdout and the table to stderr, and write both beside ``out`` (atomically). The
    env workload twice: as a first run is (its helper compiles the task's kernels beside the physics: the wall time
    a user waits) and in one process (every function's compilation in the table)."""
    code = workload(what, package)
    first = {"first_run_wall_s": measure(code)["wall_s"]} if what == "env" else {}
    report = {"what": what, "package": package, **first, **measure(code, env={SWITCH: "0"})}
    md = markdown(report, top)
    print(md, end="", file=sys.stderr)
    print(json.dumps(report, indent=2))
    if out is not None:
        from ..physics.config import atomic_write_text

        atomic_write_text(out, json.dumps(report, indent=2) + "\n")
        atomic_write_text(out.with_suffix(".md"), md)
    return 0


def _out_problem(out: Path | None) -> str | None:
    """Why ``out`` cannot be written (its folder is created where missing), before the minutes of measuring."""
    if out is None:
        return None
    if out.is_dir():
        return f"--out {str(out)!r} is a folder; give a file name such as {str(out / 'compile.json')!r}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"--out: cannot create folder {str(out.parent)!r}: {exc.strerror or exc}"
    return None


def compile_cli(out: Path | None) -> int:
    """``msdgrasp bench compile``: the env workload on this build."""
    out = None if out is None else Path(out)
    problem = _out_problem(out)
    if problem:
        print(f"msdgrasp bench: error: {problem}", file=sys.stderr)
        return 2
    return _report("env", "msdgrasp", 25, out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m msdgrasp.benchmarks.compile_time",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--what", choices=sorted(WORKLOADS), default="env", help="the workload (default: env)")
    parser.add_argument("--top", type=int, default=25, help="functions in the table (default: 25)")
    parser.add_argument("--package", default="msdgrasp",
                        help="the build measured: a package name on sys.path (default: msdgrasp, this build)")
    parser.add_argument("--out", type=Path, help="also write the report as JSON (and .md beside it)")
    args = parser.parse_args(argv)
    if args.top < 1:
        parser.error(f"--top must be >= 1, got {args.top}")
    if not args.package.isidentifier() or importlib.util.find_spec(args.package) is None:
        parser.error(f"--package {args.package!r} is not an importable package name")
    problem = _out_problem(args.out)
    if problem:
        parser.error(problem)
    return _report(args.what, args.package, args.top, args.out)


if __name__ == "__main__":
    sys.exit(main())
