"""Test-run-wide setup: an isolated home, a headless matplotlib, shared meshes, a compiled kernel.

The environment is set at import time, i.e. before any test module imports rerun, matplotlib or numba:

* HOME and the XDG config/data/cache dirs point into a per-run temporary folder, so nothing a test
  triggers (rerun, matplotlib, torch, tensorboard caches or telemetry state) reads or writes the real
  user's home; removed at exit. The package's result cache (the oracle's minimal forces,
  ``msdgrasp.agents.result_cache``) lives there too: shared by the run's workers and subprocesses, never
  read from an earlier run;
* MPLBACKEND=Agg (no display needed);
* NUMBA_ENABLE_CUDASIM=1 unless set: the CUDA kernels run in numba's simulator (CI has no GPU);
* NUMBA_CACHE_DIR (unless already set) is ``physics/__pycache__/numba-tests`` (kept between runs, so
  the second run is fast) or, when the package folder is not writable, the run's temporary folder.
  Stale kernels are no concern: ``msdgrasp.physics.numba_cache`` keys every physics kernel on all physics
  sources (tests/test_numba_cache.py);
* under xdist (``pytest -n N``, N >= 2) the controller compiles the common kernels into that cache before the
  workers start (:func:`pytest_configure`), so they are compiled once, not once per worker;
* in the simulator, its block manager's poll loop yields the interpreter to the simulated threads
  (:func:`_simulator_polls_yielding`).
"""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

_RUN_HOME = Path(tempfile.mkdtemp(prefix="msdgrasp-tests-home-"))
atexit.register(shutil.rmtree, _RUN_HOME, ignore_errors=True)
for _var, _sub in (("XDG_CONFIG_HOME", ".config"), ("XDG_DATA_HOME", ".local/share"), ("XDG_CACHE_HOME", ".cache")):
    (_RUN_HOME / _sub).mkdir(parents=True, exist_ok=True)
    os.environ[_var] = str(_RUN_HOME / _sub)
os.environ["HOME"] = str(_RUN_HOME)
os.environ["MPLBACKEND"] = "Agg"
# the CUDA backend's tests (tests/test_cuda*.py) run in numba's CUDA simulator unless told otherwise
# (NUMBA_ENABLE_CUDASIM=0 on a machine with a GPU); numba reads it when first imported
os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")
os.environ.setdefault("MPLCONFIGDIR", str(_RUN_HOME / ".config" / "matplotlib"))

_PHYSICS_DIR = Path(__file__).resolve().parent.parent / "physics"
if "NUMBA_CACHE_DIR" not in os.environ:
    _base = _PHYSICS_DIR / "__pycache__"
    try:
        _base.mkdir(exist_ok=True)
        if not os.access(_base, os.W_OK):
            raise PermissionError(_base)
    except OSError:
        _base = _RUN_HOME / ".cache"
    os.environ["NUMBA_CACHE_DIR"] = str(_base / "numba-tests")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

# numba's BlockManager.run, whitespace and comments removed: numba 0.68.1's loop (numba-cuda's differs only in
# formatting, so it hashes the same)
_SIMULATOR_POLL_SHA256 = "c264829179ecdf44b31304e9e0722a4b36884ef3a5baed241f9957bb984d16df"


def _simulator_polls_yielding() -> bool:
    """Make numba's CUDA simulator hand the interpreter to its threads while it polls them.

    The simulator runs a block's threads as Python threads, and its BlockManager polls them in a loop that holds the
    GIL until the interpreter's switch interval takes it away: where one thread works and the rest wait at a
    syncthreads (the kernels' serial passes: the barrier's Gauss-Seidel chain, the contacts) the poller took half
    the interpreter's time. The same loop with ``time.sleep(0)`` once per poll (which releases the GIL to a waiting
    thread) ran the GPU bench's simulator harness in 17 s instead of 55 s; what the kernels compute is unchanged (the
    threads, their syncthreads and the order the manager releases them are numba's own). Applied only where numba's
    loop is the one this copies (its normalised source's hash); returns whether it was applied.
    """
    import hashlib
    import inspect
    import re
    import time

    from numba.cuda.simulator import kernel

    source = "".join(line.split("#")[0] for line in inspect.getsource(kernel.BlockManager.run).splitlines())
    if hashlib.sha256(re.sub(r"\s+", "", source).encode()).hexdigest() != _SIMULATOR_POLL_SHA256:
        return False

    # numba's BlockManager.run (numba/cuda/simulator/kernel.py, BSD 2-Clause, Anaconda Inc. and others) with one line
    # added
    def run(self, grid_point, *args):
        threads = set()
        livethreads = set()
        blockedthreads = set()
        for block_point in np.ndindex(*self._block_dim):
            def target():
                self._f(*args)
            t = kernel.BlockThread(target, self, grid_point, block_point, self._debug)
            t.start()
            threads.add(t)
            livethreads.add(t)
        while livethreads:
            time.sleep(0)  # the only change: let a simulated thread run
            for t in livethreads:
                if t.syncthreads_blocked:
                    blockedthreads.add(t)
                elif t.exception:
                    for t_other in threads:
                        t_other.abort = True
                        t_other.syncthreads_blocked = False
                        t_other.syncthreads_event.set()
                    raise t.exception[0].with_traceback(t.exception[1])
            if livethreads == blockedthreads:
                for t in blockedthreads:
                    t.syncthreads_blocked = False
                    t.syncthreads_event.set()
                blockedthreads = set()
            livethreads = set([t for t in livethreads if t.is_alive()])
        for t in threads:
            if t.exception:
                raise t.exception[0].with_traceback(t.exception[1])

    kernel.BlockManager.run = run
    return True


_SIMULATOR_YIELDS = os.environ["NUMBA_ENABLE_CUDASIM"] == "1" and _simulator_polls_yielding()


def pytest_report_header(config: pytest.Config) -> str | None:
    if os.environ["NUMBA_ENABLE_CUDASIM"] != "1":
        return None
    return ("numba CUDA simulator: its poll loop yields to the simulated threads" if _SIMULATOR_YIELDS else
            "numba CUDA simulator: its poll loop is not the one conftest.py patches; left as shipped (slower)")


@pytest.fixture(scope="session")
def sphere_coarse():
    """The paper's test sample: a 50 mm sphere, coarse mesh (216 nodes)."""
    from msdgrasp.physics.mesh_gen import sphere_mesh

    return sphere_mesh(0.05, "coarse")


@pytest.fixture(scope="session")
def spleen_coarse():
    """The built-in spleen, coarse mesh (~240 nodes, node set "hilum")."""
    from msdgrasp.physics.mesh_gen import spleen_mesh

    return spleen_mesh("coarse")


@pytest.fixture(scope="session")
def compiled_kernel(sphere_coarse):
    """Compile (or load from numba's cache) the simulate kernel once per test run: one 1 ms step of a
    sphere between two plates, so later timings measure physics, not compilation."""
    from msdgrasp.physics.simulation import Plate, Simulation
    from msdgrasp.physics.tissue import TissueModel, TissueParams

    model = TissueModel.from_params(sphere_coarse, TissueParams(youngs_modulus_pa=60e3))
    z = sphere_coarse.nodes[:, 2]
    sim = Simulation(
        model, 1, plates=[Plate((0.0, 0.0, float(z.min())), (0.0, 0.0, 1.0)),
                          Plate((0.0, 0.0, float(z.max())), (0.0, 0.0, -1.0))]
    )
    sim.step(1)
    assert np.all(sim.finite())
    return True


# What an xdist controller compiles before its workers start, in two parallel processes: the env's path (the scene's
# simulate in float64 and the task kernels) and the float32 simulate (tests/test_float32.py, the CUDA tests' float32
# reference), the workloads of `python -m msdgrasp.benchmarks.compile_time`. From an empty cache each worker, and each
# subprocess a test starts meanwhile, would compile the same kernels at once (the env's path alone takes ~110 s on one
# core), and the compilation would land in the durations of whichever tests came first (`--durations` would name them
# slow); compiled once here, they all load them from NUMBA_CACHE_DIR. With a warm cache this takes a few seconds.
_WARM_UP = ("env", "float32")


@pytest.hookimpl(trylast=True)
def pytest_configure(config: pytest.Config) -> None:
    """On an xdist controller (``pytest -n N``, N >= 2), compile the common kernels into numba's cache first."""
    import subprocess
    import sys
    import time

    workers = getattr(config.option, "numprocesses", None)
    if hasattr(config, "workerinput") or not isinstance(workers, int) or workers < 2:
        return
    from msdgrasp.benchmarks.compile_time import workload

    reporter = config.pluginmanager.get_plugin("terminalreporter")
    t0 = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", workload(what)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for what in _WARM_UP]
    for proc in procs:
        _, err = proc.communicate()
        if proc.returncode != 0:  # the tests that build these will fail with the full error; say it here too
            print(f"conftest: compiling the kernels ahead failed (exit {proc.returncode}): {err[-2000:]}",
                  file=sys.stderr)
    if reporter is not None:
        reporter.write_line(f"compiled or loaded the common numba kernels ({', '.join(_WARM_UP)}) in "
                            f"{time.perf_counter() - t0:.0f} s, before the workers start")
