"""A disk cache for deterministic results of the package's own simulations that take seconds to compute and are
asked for again and again: the oracle's minimal slip-free force at a friction coefficient (a bisection over whole
episodes, 6-16 s per mu on two cores), which every evaluation, multi-seed report, sweep point and oracle episode
needs, each in a process of its own.

An entry is keyed on

* what the caller computed it from (``key``: the task config, mu, ...), as canonical JSON;
* every file of the package a simulation's result can depend on: the sources of ``physics/``, ``envs/``,
  ``agents/`` and ``experiments/``, the built-in configs and meshes (:func:`package_digest`), so any edit there
  computes anew;
* the numerical stack: the Python, NumPy, numba and llvmlite versions, the machine and the CPU numba compiles for
  (its kernels round as that CPU's code does).

A caller passes ``cacheable=False`` where its inputs name files outside the package (a user's tissue config), whose
edits the key could not see. Values are JSON numbers (a float's exact round trip), written atomically; an entry
that cannot be read or does not hold its key is computed again and rewritten, never guessed; an entry that
cannot be written is a warning (the value stands).

Where: ``MSDGRASP_CACHE_DIR``, else ``$XDG_CACHE_HOME/msdgrasp``, else ``~/.cache/msdgrasp``; set
``MSDGRASP_CACHE_DIR`` to an empty value to turn the cache off.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import platform
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..physics.config import atomic_write

PACKAGE_DIR = Path(__file__).resolve().parent.parent
#: the package's folders whose files can change a simulation's result (the rest: the command line, benchmarks,
#: docs and tests)
KEYED_FOLDERS = ("physics", "envs", "agents", "experiments", "configs", "meshes")
#: bumped where the entries' layout changes
FORMAT = 1


def cache_dir() -> Path | None:
    """The cache's folder, or None where ``MSDGRASP_CACHE_DIR`` is set empty (cache off)."""
    explicit = os.environ.get("MSDGRASP_CACHE_DIR")
    if explicit is not None:
        return Path(explicit).expanduser() if explicit.strip() else None
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(xdg) if xdg else Path.home() / ".cache") / "msdgrasp"


@functools.lru_cache(maxsize=1)
def package_digest() -> str:
    """SHA-256 over the relative paths and contents of every file in :data:`KEYED_FOLDERS` (bytecode caches
    excluded), in sorted order."""
    digest = hashlib.sha256()
    for folder in KEYED_FOLDERS:
        files = sorted(p for p in (PACKAGE_DIR / folder).rglob("*") if p.is_file() and "__pycache__" not in p.parts)
        for path in files:
            digest.update(path.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


@functools.lru_cache(maxsize=1)
def stack() -> dict[str, str]:
    """The numerical stack a cached result was computed on."""
    import llvmlite
    import llvmlite.binding as llvm
    import numba
    import numpy

    return {"python": sys.version.split()[0], "numpy": numpy.__version__, "numba": numba.__version__,
            "llvmlite": llvmlite.__version__, "machine": platform.machine(), "cpu": llvm.get_host_cpu_name()}


def entry_key(kind: str, key: dict[str, Any]) -> dict[str, Any]:
    """Everything an entry of ``kind`` is keyed on (stored in the entry too)."""
    return {"format": FORMAT, "kind": kind, "key": key, "package": package_digest(), "stack": stack()}


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def cached_float(kind: str, key: dict[str, Any], compute: Callable[[], float], cacheable: bool = True) -> float:
    """``compute()``, or the value a process computed before for the same ``kind``, ``key``, package files and
    numerical stack. ``key`` must be JSON (dicts, lists, strings, finite numbers)."""
    folder = cache_dir()
    if not cacheable or folder is None:
        return float(compute())
    full = entry_key(kind, key)
    text = _canonical(full)
    path = folder / kind / f"{hashlib.sha256(text.encode()).hexdigest()}.json"
    try:
        entry = json.loads(path.read_text())
        if _canonical(entry["for"]) == text and isinstance(entry["value"], float) and math.isfinite(entry["value"]):
            return entry["value"]
    except (OSError, ValueError, KeyError, TypeError):
        pass  # absent, unreadable or another key's: computed below
    value = float(compute())
    if math.isfinite(value):
        body = json.dumps({"for": full, "value": value}, indent=1) + "\n"
        try:
            atomic_write(path, lambda p: p.write_text(body))
        except OSError as exc:  # the value stands; the next process computes it again
            warnings.warn(f"msdgrasp result cache: cannot write {path} ({exc}); set MSDGRASP_CACHE_DIR to a "
                          f"writable folder, or empty to turn the cache off", RuntimeWarning, stacklevel=2)
    return value
