"""The command line's input error: one line on stderr, exit status 2 (``msdgrasp`` and ``python -m``).

It lives in a leaf module so that every command module raises the same class object: defined inside
``cli/main.py``, ``python -m msdgrasp.cli.main`` runs that file as ``__main__``, whose UsageError is a
different class than the one the command modules import, and a bad path printed a traceback (exit 1).
"""

from __future__ import annotations

from ..physics.config import ConfigError


class UsageError(ConfigError):
    """Bad command-line input: printed as one line, exit status 2."""
