"""The compile helper's program (:mod:`.compile_helper` starts it): the task's kernels compiled, and cached, by a
one-env core that simulates nothing::

    python -m msdgrasp.envs.first_run CONFIG_JSON PRECISION
"""

from __future__ import annotations

import json
import os
import sys
from typing import TYPE_CHECKING

import numpy as np

from .compile_helper import SWITCH

if TYPE_CHECKING:
    from .core import GraspLiftConfig


def compile_task_kernels(config: GraspLiftConfig, precision: str) -> None:
    """In this process: a one-env core on the unsettled scene through a reset and a step that advances no tissue,
    which compiles (and caches) the task's kernels and simulates nothing."""
    from ..physics import scenario
    from .core import GraspLiftCore

    def unsettled(model, x0=None, time_s=0.0, dt=1e-3, safety=0.0):
        return np.array(model.rest_positions if x0 is None else x0, dtype=np.float64), np.zeros(len(model.edges))

    scenario.settle = unsettled  # (this process only compiles)
    os.environ[SWITCH] = "0"
    core = GraspLiftCore(config, 1, precision)
    core.seed(0, 0)
    core.reset(0)
    core.step(np.zeros((1, 2)), advance=np.empty(0, dtype=np.int64))


def main(argv: list[str] | None = None) -> int:
    from ..physics.config import from_dict
    from .core import GraspLiftConfig

    config_json, precision = (sys.argv[1:] if argv is None else argv)
    compile_task_kernels(from_dict(GraspLiftConfig, json.loads(config_json)), precision)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
