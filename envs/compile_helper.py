"""A first run compiles on two cores: the task's kernels in a helper process beside the physics.

A fresh install compiles every kernel on its first call, one after the other on one core: the physics'
``simulate`` (which settling the scene needs first) and then the task's kernels (a reset and a step). The two
sets share almost nothing, so where the task's kernels are not in numba's cache and the machine has a second
core, :class:`.core.GraspLiftCore` starts :func:`helper`: a process that compiles them (into the same cache)
while the core settles its scene, and waits for it before its first reset, which then loads them. The helper
simulates nothing: its scene is the unsettled tissue (the kernels' types do not depend on the values) and its
step advances no tissue. Where it fails, the core compiles what it did not, as without it. The environment
variable ``MSDGRASP_COMPILE_HELPER=0`` switches it off.

This module starts and waits for the helper; :mod:`.first_run` is the helper's program::

    python -m msdgrasp.envs.first_run CONFIG_JSON PRECISION
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

#: the longest a core waits for its helper, s (it compiles in about half a minute on one core)
HELPER_TIMEOUT_S = 600.0
#: the environment variable that switches the helper off ("0"); the helper's program sets it, so that its core
#: starts no helper of its own
SWITCH = "MSDGRASP_COMPILE_HELPER"
#: whether this process has started a helper: at most one, so that where the cache cannot be written (the helper's
#: work then lost) every later core does not wait for another
_started = False


def task_kernels_cached() -> bool:
    """Whether numba's cache has an index for the task's reset kernel for Python callers: then the task's kernels
    load (or, after an edit of their sources, the core compiles them itself), and a helper would only cost a
    process. (The index's contents name the task's record types, which exist only once a core has built its
    records: its file is what can be asked before.)"""
    from .task import start_episode

    try:  # (numba's private cache API; without it, or without jit, no helper)
        return os.path.exists(start_episode.python_twin()._cache._cache_file._index_path)
    except Exception:
        return True


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the OS says, e.g. under ``taskset``; else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def helper(config: Any, precision: str) -> subprocess.Popen | None:
    """Start the helper that compiles the task's kernels for ``config`` (a :class:`.core.GraspLiftConfig`; this module
    is below the core, which starts it) and ``precision``; None where they are cached, where the machine has one core
    (there it would only compete with the physics' compilation) or where this process has started one before."""
    global _started
    if _started or os.environ.get(SWITCH) == "0" or usable_cores() < 2 or task_kernels_cached():
        return None
    _started = True
    from ..physics.config import to_dict

    if not sys.executable or "python" not in os.path.basename(sys.executable).lower():
        return None  # (an embedding host's executable is not Python's)
    try:
        return subprocess.Popen([sys.executable, "-m", f"{__package__}.first_run", json.dumps(to_dict(config)),
                                 precision], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    except OSError:  # the core compiles everything itself, as without a helper
        return None


def join(process: subprocess.Popen | None) -> None:
    """Wait for a helper (at most :data:`HELPER_TIMEOUT_S`; one that runs longer is stopped)."""
    if process is None:
        return
    try:
        process.wait(timeout=HELPER_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        stop(process)


def stop(process: subprocess.Popen | None) -> None:
    """Stop a helper and reap it (None: nothing to stop)."""
    if process is not None:
        process.kill()
        process.wait()


@contextlib.contextmanager
def beside(config: Any, precision: str) -> Iterator[subprocess.Popen | None]:
    """A helper (:func:`helper`) for the block's duration: joined when the block ends, stopped when it raises (a core
    whose construction fails leaves no process compiling behind it)."""
    process = helper(config, precision)
    try:
        yield process
    except BaseException:
        stop(process)
        raise
    join(process)
