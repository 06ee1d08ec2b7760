"""A batch of the benchmark task through ``gym.make_vec`` and Gymnasium's vector wrappers.

    python examples/vector_env.py --num-envs 16 --steps 400

``vectorization_mode="vector_entry_point"`` builds the package's own batched env (one numba call advances every
tissue), not N copies of the single env: so ``make_vec``'s ``wrappers=`` argument (per sub-env wrappers) does not
apply, and Gymnasium's *vector* wrappers (``gymnasium.wrappers.vector``) wrap the batch instead. The batch resets a
finished sub-env on the step after its last (``autoreset_mode`` NEXT_STEP), which those wrappers follow.

Steps the batch with random actions and prints each finished episode's return and length (RecordEpisodeStatistics),
the success rate over them, and the running mean of the normalised observation (NormalizeObservation).
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from gymnasium.wrappers.vector import ClipAction, NormalizeObservation, RecordEpisodeStatistics

import msdgrasp  # noqa: F401  registers msdgrasp/GraspLift-v2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=400, help="batch steps (33 ms of simulated time each)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    envs = gym.make_vec("msdgrasp/GraspLift-v2", num_envs=args.num_envs, vectorization_mode="vector_entry_point")
    print(f"{type(envs).__name__}: {envs.num_envs} envs, autoreset {envs.metadata['autoreset_mode'].name}, "
          f"single observation {envs.single_observation_space.shape}, single action {envs.single_action_space}")
    envs = NormalizeObservation(RecordEpisodeStatistics(ClipAction(envs)))
    envs.action_space.seed(args.seed)
    obs, info = envs.reset(seed=args.seed)  # sub-env i is seeded seed + i
    successes: list[bool] = []
    for _ in range(args.steps):
        obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        done = terminated | truncated
        if done.any():
            successes += [bool(s) for s in np.asarray(info["is_success"])[done]]
        if "episode" in info:
            for i in np.flatnonzero(info["_episode"]):
                print(f"env {i:2d}: episode return {info['episode']['r'][i]:8.2f}, "
                      f"length {info['episode']['l'][i]} steps")
    if successes:
        print(f"{len(successes)} episodes finished, success rate {np.mean(successes):.2f}")
    else:
        print("no episode finished yet (an episode lasts at most 304 steps)")
    print(f"observation after NormalizeObservation: mean {obs.mean():+.3f}, std {obs.std():.3f} "
          f"over {envs.obs_rms.count:.0f} samples")
    envs.close()


if __name__ == "__main__":
    main()
