"""A user's own plain Stable-Baselines3 PPO on the registered env: default hyper-parameters, one env.

    pip install 'msdgrasp[train]'
    python examples/plain_sb3_ppo.py --steps 300000 --seed 0 --eval-episodes 10

Prints, every 16384 steps, the success rate and mean peak pinch of the last 100 training episodes
(stochastic policy, friction drawn from the env's training range), and at the end evaluates the
deterministic policy with ``msdgrasp``'s evaluation (``--eval-episodes`` at mu 0.3, 0.5, 0.7, 0.9) on the env's task:
``msdgrasp/GraspLift-v2``, the benchmark task, whose every observation entry comes from a named sensor.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

import msdgrasp  # noqa: F401  registers msdgrasp/GraspLift-v2
from msdgrasp.agents.model_policy import ModelPolicy
from msdgrasp.agents.evaluation import evaluate_policy


class Progress(BaseCallback):
    def __init__(self, every: int = 16384) -> None:
        super().__init__()
        self.every, self.next, self.t0, self.episodes = every, every, time.perf_counter(), []

    def _on_step(self) -> bool:
        for info, done in zip(self.locals["infos"], self.locals["dones"]):
            if done:
                self.episodes.append((info["is_success"], info["peak_pinch_N"]))
        if self.num_timesteps >= self.next:
            self.next += self.every
            last = np.array(self.episodes[-100:], dtype=float).reshape(-1, 2)
            print(f"{self.num_timesteps:>7} steps  {time.perf_counter() - self.t0:6.0f} s  "
                  f"episodes {len(self.episodes):>5}  "
                  f"success(last 100) {last[:, 0].mean() if len(last) else float('nan'):.2f}  "
                  f"peak pinch {last[:, 1].mean() if len(last) else float('nan'):.2f} N", flush=True)
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=10, help="evaluation episodes per mu")
    args = parser.parse_args()
    torch.set_num_threads(1)  # small layers: more threads only contend with the physics (30 ms a pass, not 0.1)
    env = gym.make("msdgrasp/GraspLift-v2")
    model = PPO("MlpPolicy", env, seed=args.seed, device="cpu")  # SB3's defaults, nothing tuned
    model.learn(args.steps, callback=Progress())
    rows = evaluate_policy(ModelPolicy.from_model(model, "plain PPO"), [0.3, 0.5, 0.7, 0.9], args.eval_episodes,
                           env.unwrapped.config)
    print("deterministic policy: " + ", ".join(
        f"mu {r['mu']:g}: success {r['success_rate']:.1f}, peak pinch {r['mean_peak_pinch_N']:.2f} N" for r in rows))


if __name__ == "__main__":
    main()
