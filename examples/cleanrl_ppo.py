"""A CleanRL-style single-file PPO (continuous actions) on ``msdgrasp/GraspLift-v2``.

    pip install 'msdgrasp[train]'
    python examples/cleanrl_ppo.py --total-timesteps 1000000 --num-envs 16

After CleanRL's ``ppo_continuous_action.py``: one file, a dataclass of arguments, the package's batched env through
``gym.make_vec`` with Gymnasium's vector wrappers (statistics, action clipping, observation and reward normalisation),
GAE, a clipped surrogate, a clipped value loss. One difference: the batched env resets a finished sub-env on the step
*after* its last (``autoreset_mode`` NEXT_STEP): that step's action is ignored, so its transition is left out of
the loss (``valid``), and GAE stops at the episode's end as CleanRL's does. Truncation counts as an end, as there.
Prints, per iteration, the steps, the mean return and success rate of the episodes finished since the last print.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from gymnasium.wrappers import vector as vw
from torch.distributions.normal import Normal

import msdgrasp  # noqa: F401  registers msdgrasp/GraspLift-v2


@dataclass
class Args:
    env_id: str = "msdgrasp/GraspLift-v2"  # the Gymnasium id
    seed: int = 0  # seeds torch, numpy and the envs (sub-env i: seed + i)
    total_timesteps: int = 1_000_000  # agent steps over all envs
    num_envs: int = 16  # sub-envs of the batched env
    num_steps: int = 128  # steps per env per rollout
    learning_rate: float = 3e-4  # Adam's, annealed linearly to 0
    gamma: float = 0.99  # discount
    gae_lambda: float = 0.95  # GAE's lambda
    num_minibatches: int = 8  # minibatches per epoch
    update_epochs: int = 10  # epochs per rollout
    clip_coef: float = 0.2  # the surrogate's (and the value's) clip
    ent_coef: float = 0.0  # entropy bonus
    vf_coef: float = 0.5  # value loss weight
    max_grad_norm: float = 0.5  # gradient clip
    save: str = ""  # a path to save the agent's state_dict to at the end (empty: none)


def parse_args() -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for f in dataclasses.fields(Args):
        parser.add_argument("--" + f.name.replace("_", "-"), type=type(f.default), default=f.default)
    return Args(**vars(parser.parse_args()))


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(), layer_init(nn.Linear(64, 64)),
                                    nn.Tanh(), layer_init(nn.Linear(64, 1), std=1.0))
        self.actor_mean = nn.Sequential(layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(), layer_init(nn.Linear(64, 64)),
                                        nn.Tanh(), layer_init(nn.Linear(64, act_dim), std=0.01))
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        mean = self.actor_mean(x)
        probs = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.critic(x)


def main() -> None:
    args = parse_args()
    batch_size = args.num_envs * args.num_steps
    minibatch_size = max(batch_size // args.num_minibatches, 1)
    num_iterations = max(args.total_timesteps // batch_size, 1)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small layers: more threads only contend with the physics (30 ms a pass, not 0.1)

    envs = gym.make_vec(args.env_id, num_envs=args.num_envs, vectorization_mode="vector_entry_point")
    envs = vw.RecordEpisodeStatistics(envs)
    envs = vw.ClipAction(envs)
    envs = vw.NormalizeObservation(envs)
    envs = vw.TransformObservation(envs, lambda o: np.clip(o, -10, 10))
    envs = vw.NormalizeReward(envs, gamma=args.gamma)
    envs = vw.TransformReward(envs, lambda r: np.clip(r, -10, 10))
    obs_dim, act_dim = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]
    agent = Agent(obs_dim, act_dim)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    obs = torch.zeros((args.num_steps, args.num_envs, obs_dim))
    actions = torch.zeros((args.num_steps, args.num_envs, act_dim))
    logprobs, rewards, dones, values, valid = (torch.zeros((args.num_steps, args.num_envs)) for _ in range(5))

    global_step, start = 0, time.time()
    next_obs = torch.tensor(envs.reset(seed=args.seed)[0], dtype=torch.float32)
    next_done = torch.zeros(args.num_envs)  # obs is an episode's last (its next step is the batch's reset)
    returns, successes = [], []
    for iteration in range(1, num_iterations + 1):
        optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / num_iterations) * args.learning_rate
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs[step], dones[step], valid[step] = next_obs, next_done, 1.0 - next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
            values[step], actions[step], logprobs[step] = value.flatten(), action, logprob
            o, r, term, trunc, info = envs.step(action.numpy())
            end = np.logical_or(term, trunc)
            rewards[step] = torch.tensor(r, dtype=torch.float32)
            next_obs, next_done = torch.tensor(o, dtype=torch.float32), torch.tensor(end, dtype=torch.float32)
            if "episode" in info:
                returns += list(info["episode"]["r"][info["_episode"]])
            if end.any():
                successes += [bool(s) for s in np.asarray(info["is_success"])[end]]

        with torch.no_grad():  # GAE; nextnonterminal 0 where the next obs is a reset (the episode ended)
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages, lastgaelam = torch.zeros_like(rewards), 0
            for t in reversed(range(args.num_steps)):
                nextnonterminal = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                nextvalues = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * nextvalues * nextnonterminal - values[t]
                advantages[t] = lastgaelam = delta + args.gamma * args.gae_lambda * nextnonterminal * lastgaelam
            returns_t = advantages + values

        b_obs, b_actions = obs.reshape(-1, obs_dim), actions.reshape(-1, act_dim)
        b_logprobs, b_adv, b_ret, b_val = (x.reshape(-1) for x in (logprobs, advantages, returns_t, values))
        b_inds = torch.nonzero(valid.reshape(-1)).flatten().numpy()  # the autoreset steps left out
        for _ in range(args.update_epochs):
            np.random.shuffle(b_inds)
            for s in range(0, len(b_inds), minibatch_size):
                mb = b_inds[s:s + minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_actions[mb])
                ratio = (newlogprob - b_logprobs[mb]).exp()
                mb_adv = b_adv[mb]
                mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std(unbiased=False) + 1e-8)
                pg_loss = torch.max(-mb_adv * ratio,
                                    -mb_adv * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()
                newvalue = newvalue.view(-1)
                v_clipped = b_val[mb] + torch.clamp(newvalue - b_val[mb], -args.clip_coef, args.clip_coef)
                v_loss = 0.5 * torch.max((newvalue - b_ret[mb]) ** 2, (v_clipped - b_ret[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()

        ret = f"{np.mean(returns):8.2f}" if returns else "       -"
        succ = f"{np.mean(successes):.2f}" if successes else "-"
        print(f"iteration {iteration}/{num_iterations}  steps {global_step}  {time.time() - start:6.0f} s  "
              f"episodes {len(returns)}  return {ret}  success {succ}  loss {loss.item():.3f}", flush=True)
        returns, successes = [], []
    if args.save:
        torch.save(agent.state_dict(), args.save)
    envs.close()


if __name__ == "__main__":
    main()
