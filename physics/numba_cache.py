"""numba's on-disk cache, keyed on ALL physics sources instead of each jitted function's own file.

numba checks a cached function against the source of its own file only. ``integrator.simulate`` inlines
kernels from ``contact.py`` and ``forces.py``, so after an edit of those files a cached ``simulate``
would keep running the old physics. Importing this module (``physics/__init__.py`` does, before any
kernel module) puts locators in front of numba's own for the functions defined in this folder; they are
numba's locators (same cache folders: ``NUMBA_CACHE_DIR``, else ``__pycache__``, else the user cache)
with one change: the source stamp is a hash of every ``*.py`` file in ``physics/``. Any edit there
invalidates every cached physics kernel; functions of other packages are not affected.

A module above physics whose kernels compile in physics constants or inline physics functions (the task's
``envs/task.py`` reads the readout columns ``J_*`` and ``G_*``) registers its file with :func:`key_on_physics`
before its first kernel runs: its functions are then stamped with all physics sources *and* their own file.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

from numba.core import caching as _caching


def _numba_class(name: str):
    """numba >= 0.61 names these classes without the leading underscore; older releases with it."""
    for candidate in (name, "_" + name):
        if hasattr(_caching, candidate):
            return getattr(_caching, candidate)
    raise ImportError(f"numba {_caching.__name__}: neither {name} nor _{name} exists; msdgrasp's cache keying "
                      f"needs numba's cache locators (numba >= 0.60)")


CacheImpl = _numba_class("CacheImpl")
InTreeCacheLocator = _numba_class("InTreeCacheLocator")
UserProvidedCacheLocator = _numba_class("UserProvidedCacheLocator")
UserWideCacheLocator = _numba_class("UserWideCacheLocator")

PHYSICS_DIR = Path(__file__).resolve().parent


def sources_digest(folder: Path = PHYSICS_DIR) -> str:
    """SHA-256 over the names and contents of the ``*.py`` files in ``folder`` (sorted by name)."""
    digest = hashlib.sha256()
    for src in sorted(Path(folder).glob("*.py")):
        digest.update(src.name.encode() + b"\0" + src.read_bytes() + b"\0")
    return digest.hexdigest()


@functools.lru_cache(maxsize=1)
def _physics_digest() -> str:
    return sources_digest(PHYSICS_DIR)


#: files outside physics/ whose cached functions are keyed on the physics sources too (:func:`key_on_physics`)
_KEYED_FILES: set[Path] = set()


def key_on_physics(py_file: str | Path) -> None:
    """Stamp the cached numba functions of ``py_file`` with every physics source and the file itself, so an
    edit of a physics constant or function they compile in invalidates them (call it at the file's import)."""
    _KEYED_FILES.add(Path(py_file).resolve())


@functools.lru_cache(maxsize=None)
def _keyed_file_digest(path: Path) -> str:
    return hashlib.sha256(_physics_digest().encode() + b"\0" + path.read_bytes()).hexdigest()


def _source_path(py_file) -> Path | None:
    try:
        return Path(py_file).resolve()
    except OSError:
        return None


class _AllPhysicsSourcesStamp:
    """Locator mixin: handle only functions defined in physics/ (or a :func:`key_on_physics` file), stamped
    with all physics sources (and their own file)."""

    def get_source_stamp(self) -> str:
        path = _source_path(self._py_file)
        return _physics_digest() if path is None or path.parent == PHYSICS_DIR else _keyed_file_digest(path)

    @classmethod
    def from_function(cls, py_func, py_file):
        path = _source_path(py_file)
        inside = path is not None and (path.parent == PHYSICS_DIR or path in _KEYED_FILES)
        return super().from_function(py_func, py_file) if inside else None


class PhysicsUserProvidedLocator(_AllPhysicsSourcesStamp, UserProvidedCacheLocator):
    pass


class PhysicsInTreeLocator(_AllPhysicsSourcesStamp, InTreeCacheLocator):
    pass


class PhysicsUserWideLocator(_AllPhysicsSourcesStamp, UserWideCacheLocator):
    pass


LOCATORS = (PhysicsUserProvidedLocator, PhysicsInTreeLocator, PhysicsUserWideLocator)


def install() -> None:
    """Put the physics locators first in numba's search order (idempotent)."""
    classes = CacheImpl._locator_classes
    if classes[: len(LOCATORS)] != list(LOCATORS):
        classes[:0] = [c for c in LOCATORS if c not in classes]


install()
