"""Physics: tissue, grasper, contact and their numba kernels (imports nothing above it).

Importing the package first keys numba's cache of every kernel here on all physics sources
(:mod:`.numba_cache`).
"""

from . import numba_cache  # noqa: F401  (must run before any kernel module is imported)
