"""Evaluate your own policy: any object with ``name``, ``reset(infos)`` and ``act(obs)``.

    python examples/own_policy.py --episodes 10 --out logs/own_policy

The evaluation runs a policy on a batch of episodes side by side (docs/learners.md, "Policies, and policies with
memory"): ``reset(infos)`` gets one reset info per slot before the first step, ``act(obs)`` maps the batch's
observations (B, 32) to actions (B, 2) in [-1, 1], once per agent step, slots never reordered.

1. Python API: ``agents.rollout.evaluate_policy`` runs the object at the friction coefficients you give, on the sealed
   evaluation seeds, and returns one row of metrics per mu.
2. The command line takes a policy as a spec: a saved model (``--policy RUN/seed_0/best_model.zip``) or a
   registered controller. A script registers its class (``register_controller``) and calls the command line's
   ``main`` in the same process; this runs here as (the suite on a subset of its conditions and episodes)::

       msdgrasp evaluate --suite in_range --no-baselines --policy steady --episodes N --condition nominal --out DIR

   Leave out ``--workers``/``--ray``: worker processes import the package, not this script, so they would not know
   ``steady``. The suite writes ``DIR/suite_in_range.json`` for ``msdgrasp leaderboard`` (docs/benchmark.md).
"""

from __future__ import annotations

import argparse
from typing import Any, Sequence

import numpy as np

from msdgrasp.agents.controller_registry import register_controller
from msdgrasp.agents.protocol import EVALUATION_SEED
from msdgrasp.agents.rollout import evaluate_policy
from msdgrasp.cli.main import main as msdgrasp_cli
from msdgrasp.envs.core import GraspLiftConfig, benchmark_config


class SteadyGrip:
    """A steady pinch set-point (action 0.2: 1.8 N) and a pull slower than action 0's 10 mm/s, whatever it senses."""

    name = "steady grip"

    def __init__(self, config: GraspLiftConfig | None = None, grip: float = 0.2, pull: float = -0.4) -> None:
        self.action = np.array([grip, pull], dtype=np.float32)

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        self.batch = len(infos)  # a stateful policy would clear its memory here, per slot

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.tile(self.action, (len(obs), 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10, help="episodes per mu (the suite's protocol: 19)")
    parser.add_argument("--out", default="logs/own_policy", help="folder of the command line's suite result")
    args = parser.parse_args()

    # 1. the Python API, on the v2 benchmark task
    rows = evaluate_policy(SteadyGrip(), [0.3, 0.5, 0.8], args.episodes, benchmark_config(), seed=EVALUATION_SEED)
    for r in rows:
        print(f"mu {r['mu']:g}: success {r['success_rate']:.2f}, mean peak pinch {r['mean_peak_pinch_N']:.2f} N, "
              f"time to lift {r['mean_time_to_lift_s']:.1f} s")

    # 2. the command line, in this process: the class registered as the controller "steady"
    register_controller("steady", SteadyGrip, display="steady grip", help="a steady grip, then a slow pull")
    code = msdgrasp_cli(["evaluate", "--suite", "in_range", "--no-baselines", "--policy", "steady", "--episodes",
                         str(args.episodes), "--condition", "nominal", "--out", args.out, "--quiet"])
    print(f"msdgrasp evaluate exited {code}; suite result in {args.out}/suite_in_range.json")
    raise SystemExit(code)


if __name__ == "__main__":
    main()
