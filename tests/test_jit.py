"""The package's jit decorator (`msdgrasp.physics.jit.kernel`): what a jitted caller links is compiled without
numba's CPython and C wrappers, a call from Python runs the kernel's twin with them, and a first compilation says
so once on stderr. Each check runs in a child with an empty numba cache of its own (a cached kernel is loaded, not
compiled)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from msdgrasp.physics.jit import NOTICE

TOY = '''
from msdgrasp.physics.jit import kernel


@kernel
def double(x):
    return 2.0 * x


@kernel
def quadruple(x):
    return double(double(x))
'''

CHECK = '''
import json
from toy_kernels import double, quadruple
from msdgrasp.physics.jit import KernelDispatcher, PYTHON_CALL_SUFFIX
out = {"kernels": isinstance(double, KernelDispatcher) and isinstance(quadruple, KernelDispatcher),
       "quadruple": quadruple(1.5)}


def wrapped(cres):
    return cres.fndesc.llvm_cpython_wrapper_name in cres.library.get_llvm_str()


# compiled for quadruple's twin (none where it came from the cache): without wrappers
out["linked_wrapped"] = [wrapped(c) for c in double.overloads.values()]
out["double"] = double(2.0)  # from Python: the twin, compiled with its wrappers
twin = double.python_twin()
out["twin_name"] = twin.py_func.__qualname__
out["twin_same_code"] = twin.py_func.__code__ is double.py_func.__code__
out["twin_wrapped"] = [wrapped(c) for c in twin.overloads.values()]
out["get_overload"] = twin.get_overload(twin.signatures[0])(3.0)  # (the twin's: callable from Python)
out["linked_versions"] = len(double.overloads)
print(json.dumps(out))
'''


def _run(tmp_path, cache):
    (tmp_path / "toy_kernels.py").write_text(TOY)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(tmp_path)}
    return subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, env=env, timeout=280,
                          cwd=tmp_path)


@pytest.mark.timeout(300)
def test_a_kernel_linked_by_a_jitted_caller_has_no_wrappers_and_a_python_call_runs_its_twin(tmp_path):
    proc = _run(tmp_path, tmp_path / "cache")
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"kernels": True, "quadruple": 6.0, "linked_wrapped": [False], "double": 4.0,
                   "twin_name": "double.python_call", "twin_same_code": True, "twin_wrapped": [True],
                   "get_overload": 6.0,
                   "linked_versions": 1}  # (the Python call did not compile the linked version again)


@pytest.mark.timeout(300)
def test_the_first_compilation_of_a_package_kernel_says_so_once_on_stderr_and_a_cached_run_says_nothing(tmp_path):
    code = ("from toy_kernels import quadruple\n"
            "quadruple(1.0)\n"  # (not the package's: no notice)
            "from msdgrasp.physics.integrator import maxwell_factors\n"
            "maxwell_factors(1e-3, 1.5); maxwell_factors(1e-3, 2.0); maxwell_factors(1e-3, 2)\n")
    (tmp_path / "toy_kernels.py").write_text(TOY)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(tmp_path)}
    first, again = (subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                                   timeout=280, cwd=tmp_path) for _ in range(2))
    assert first.returncode == again.returncode == 0, first.stderr + again.stderr
    assert first.stderr.strip() == NOTICE  # once, for two signatures
    assert NOTICE not in again.stderr


@pytest.mark.timeout(300)
def test_the_notice_leaves_numbas_other_compilations_alone_and_no_jit_gives_the_python_function(tmp_path):
    """A function numba compiles that is not the package's (here one made by exec, whose ``__module__`` is None, as
    numba's own jitclass and structref constructors are) compiles as without the package, and prints nothing; with
    ``NUMBA_DISABLE_JIT=1`` a kernel is its plain Python function, as ``njit`` gives."""
    code = ("import msdgrasp.physics.jit\n"
            "from numba import njit\n"
            "ns = {}\nexec('def f(x):\\n    return x + 1', ns)\n"
            "assert ns['f'].__module__ is None and njit(ns['f'])(1) == 2\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=280)
    assert proc.returncode == 0 and NOTICE not in proc.stderr, proc.stderr
    code = ("from msdgrasp.physics.jit import kernel\n"
            "def g(x):\n    return x + 1\n"
            "assert kernel(g) is g and kernel(inline='always')(g) is g\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**env, "NUMBA_DISABLE_JIT": "1"}, timeout=280)
    assert proc.returncode == 0, proc.stderr
