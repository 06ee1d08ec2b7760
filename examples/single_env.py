"""One env of the benchmark task, stepped by hand: what ``reset`` and ``step`` return.

    python examples/single_env.py --steps 20

Makes ``msdgrasp/GraspLift-v2``, resets it with friction pinned (mu 0.5), then steps it with a simple action: the
pinch-force set-point at action 0.2 (1.8 N: 5 N x ((a + 1) / 2)^2) and a pull slower than action 0's 10 mm/s.
Prints each step's reward and the info entries that tell how the grasp goes (lift, slip, pinch force), and what the
episode's last step returned.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import msdgrasp  # noqa: F401  registers msdgrasp/GraspLift-v2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60, help="agent steps to run (33 ms each)")
    parser.add_argument("--mu", type=float, default=0.5, help="friction coefficient pinned for the episode")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    env = gym.make("msdgrasp/GraspLift-v2")
    obs, info = env.reset(seed=args.seed, options={"mu": args.mu})
    print(f"observation space {env.observation_space.shape}, action space {env.action_space}")
    print(f"reset: obs[:6] = {np.round(obs[:6], 3)}, info keys = {sorted(info)}")
    # a fixed action: grip set-point above action 0's 1.25 N, pull slower than action 0's 10 mm/s
    action = np.array([0.2, -0.4], dtype=np.float32)
    total = 0.0
    for t in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(action)
        total += float(reward)
        print(f"step {t:3d}: reward {reward:+7.3f}  lifted {1e3 * info['lifted_m']:5.1f} mm  "
              f"slip {1e3 * info['lift_slip_m']:5.2f} mm  pinch {info['pinch_force_N']:.2f} N  "
              f"peak {info['peak_pinch_N']:.2f} N  terminated={terminated} truncated={truncated}")
        if terminated or truncated:
            print(f"episode over: success={bool(info['is_success'])}")
            break
    print(f"return over {t + 1} steps: {total:.3f}; last step's info keys: {sorted(info)}")
    env.close()


if __name__ == "__main__":
    main()
