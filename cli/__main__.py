"""``python -m msdgrasp.cli``: the ``msdgrasp`` command."""

import sys

from .main import main

sys.exit(main())
