"""The package's one jit decorator for CPU kernels, and the notice a first run prints while it compiles.

``@kernel`` is numba's ``njit(cache=True, error_model="numpy")`` with one change: what a jitted caller links is
compiled without the two wrappers numba builds for every function (a CPython wrapper that unboxes each argument
from Python objects, and a C-callable one). A kernel called only from other kernels never needs them, and for the
task's records of a few hundred fields they are a sixth of a cold first step's compilation. A call from Python
goes to the kernel's *Python twin*: the same function compiled with its wrappers, on its first Python call (and
cached apart, under its name with ``.python_call``), so every kernel stays callable from Python and tests.

A kernel's cache key stays numba's, keyed on all physics sources where :mod:`.numba_cache` says so.
"""

from __future__ import annotations

import sys
import types
from typing import Any, Callable

from numba import config as numba_config
from numba import njit
from numba.core import event
from numba.core.registry import CPUDispatcher

#: numba's options every kernel is compiled with (``error_model="numpy"``: a float division by zero gives inf
#: or nan, as numpy does, instead of raising; the physics checks finiteness where it matters)
OPTIONS: dict[str, Any] = {"error_model": "numpy"}
#: what a kernel called from other kernels goes without
NO_WRAPPERS: dict[str, bool] = {"no_cpython_wrapper": True, "no_cfunc_wrapper": True}
PYTHON_CALL_SUFFIX = ".python_call"


class KernelDispatcher(CPUDispatcher):
    """A numba dispatcher compiled without wrappers for jitted callers; a call from Python runs its twin. (Numba's
    ``get_overload``, ``overloads`` and ``compile`` hand out the linked versions, which numba itself uses: their entry
    points are not for calling from Python; the kernel, or ``python_twin().get_overload``, is.)"""

    _twin: CPUDispatcher | None = None

    def python_twin(self) -> CPUDispatcher:
        """The same function compiled with its wrappers (made on first use, cached like the kernel)."""
        if self._twin is None:
            f = self.py_func
            g = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
            g.__qualname__ = f.__qualname__ + PYTHON_CALL_SUFFIX
            g.__module__, g.__doc__ = f.__module__, f.__doc__
            options = {k: v for k, v in self.targetoptions.items() if k not in NO_WRAPPERS and k != "nopython"}
            self._twin = njit(cache=True, **options)(g)
        return self._twin

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.python_twin()(*args, **kwargs)


def kernel(fn: Callable | None = None, *, inline: str = "never") -> Any:
    """``@kernel`` or ``@kernel(inline="always")``: compile ``fn`` with numba as a package kernel (above)."""

    def wrap(f: Callable) -> KernelDispatcher:
        if numba_config.DISABLE_JIT:  # (numba's switch: the plain Python function, as njit gives)
            return f
        dispatcher = KernelDispatcher(py_func=f, locals={},
                                      targetoptions={"nopython": True, **OPTIONS, **NO_WRAPPERS, "inline": inline})
        dispatcher.enable_caching()
        return dispatcher

    return wrap if fn is None else wrap(fn)


# ------------------------------------------------------------------------------------------------
# the first run's notice
# ------------------------------------------------------------------------------------------------

#: printed once per process on stderr when numba first compiles one of the package's functions
NOTICE = ("msdgrasp: compiling the physics and task kernels (about 25 s on two cores, a minute on one); this "
          "happens once, later runs load them from numba's cache")


class _FirstCompileNotice(event.Listener):
    """Prints :data:`NOTICE` when numba starts compiling a function of this package (a load from the cache is
    not a compilation and prints nothing)."""

    said = False

    def on_start(self, ev: event.Event) -> None:
        if self.said:
            return
        try:  # (a listener's error would fail numba's compilation of whatever it was compiling)
            module = getattr(getattr(ev.data.get("dispatcher"), "py_func", None), "__module__", None)
            if isinstance(module, str) and module.split(".")[0] == __name__.split(".")[0]:
                self.said = True
                print(NOTICE, file=sys.stderr, flush=True)
        except Exception:
            pass

    def on_end(self, ev: event.Event) -> None:
        pass


_notice = _FirstCompileNotice()
event.register("numba:compile", _notice)
