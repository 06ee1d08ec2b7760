"""PPO for the recurrent actor, with a privileged critic and a behaviour-cloning anchor: the recurrent learner's second
stage (:mod:`.recurrent_training`), or, from a fresh network and without the anchor, recurrent PPO from scratch.

Each update collects one wave of whole episodes (one per env) with the actor's Gaussian actions (its mean the
student's output, a learned state-independent std), then runs ``ppo_epochs`` passes of clipped PPO over minibatches
of whole episodes: the GRU is unrolled from a zero state over each episode, exactly as it runs, so no hidden state is
stored and none goes stale. The critic is an MLP over the full observation, privileged entries included (the
episode's mu, the perturbation draws, the true lift and slip): told those, the task is close to Markov, so the critic
needs no memory (the asymmetric actor-critic of Pinto et al. 2018). Advantages are GAE over each episode.

The anchor keeps what the student learned: the pinball loss of :func:`~.recurrent.pinball` between the
actor's mean and the teacher's labels on the states the actor visits (the teacher runs in the shadow as in DAgger),
weighted by ``bc_coef`` falling linearly from its first to its second value over the stage. With a weight of 0 the
teacher's labels are never read.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from .recurrent import StudentPolicy, pad_episodes, pinball


class Wave(NamedTuple):
    """One wave of episodes, one per env, each cut to its length: per episode its observations (full, privileged
    entries included: the critic's), the actions that drove it, the teacher's labels and the rewards."""

    obs: list[np.ndarray]
    actions: list[np.ndarray]
    labels: list[np.ndarray]
    rewards: list[np.ndarray]
    success: np.ndarray
    peak_pinch_N: np.ndarray

    @property
    def steps(self) -> int:
        return int(sum(len(r) for r in self.rewards))


def run_wave(env, act: Callable[[np.ndarray, np.ndarray], np.ndarray], teacher, seeds: list[int]) -> Wave:
    """Episodes reset with ``seeds`` (one per env), driven by ``act`` (observations and the teacher's labels of them ->
    actions), the teacher run in their shadow on the same observations, labelling every step with what it would do."""
    from .controllers import idle_action

    B = env.num_envs
    obs, _ = env.reset(seed=seeds)
    teacher.reset([{"mu": float(m)} for m in env.core.mu])
    xs, ys, acts, rews = [], [], [], []
    done = np.zeros(B, dtype=bool)
    length = np.zeros(B, dtype=np.int64)
    success = np.zeros(B, dtype=bool)
    peak = np.zeros(B)
    idle = idle_action(env.config)
    for _ in range(env.config.max_episode_steps + 1):
        label = teacher.act(obs)
        action = np.asarray(act(obs, label), dtype=np.float32)
        xs.append(np.asarray(obs, dtype=np.float32))
        ys.append(label.astype(np.float32))
        acts.append(action)
        obs, rew, term, trunc, inf = env.core.step(np.where(done[:, None], idle, action),
                                                   advance=np.flatnonzero(~done))
        rews.append(np.asarray(rew, dtype=np.float32))
        live = ~done
        length[live] += 1
        ended = live & (term | trunc)
        success[ended] = inf["is_success"][ended]
        peak[ended] = env.core.peak_pinch[ended]
        done |= ended
        if done.all():
            break
    cut = [np.stack(seq, axis=1) for seq in (xs, acts, ys, rews)]  # (B, T, ...)
    obs_, acts_, labels_, rews_ = ([c[b, :length[b]] for b in range(B)] for c in cut)
    return Wave(obs_, acts_, labels_, rews_, success, peak)


def make_critic(n_in: int, hidden: int):
    """The privileged critic: full observation (normalised by the first wave's statistics) -> value."""
    import torch

    nn = torch.nn

    class Critic(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("obs_mean", torch.zeros(n_in))
            self.register_buffer("obs_std", torch.ones(n_in))
            self.net = nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                     nn.Linear(hidden, 1))

        def forward(self, x):
            return self.net((x - self.obs_mean) / self.obs_std).squeeze(-1)

    return Critic()


def set_statistics(module, frames: np.ndarray) -> None:
    """``module``'s input mean and std from ``frames`` (entries that never vary pass unscaled)."""
    import torch

    std = frames.std(axis=0)
    module.obs_mean.copy_(torch.as_tensor(frames.mean(axis=0), dtype=torch.float32))
    module.obs_std.copy_(torch.as_tensor(np.where(std > 1e-6, std, 1.0), dtype=torch.float32))


def gae(rewards: np.ndarray, values: np.ndarray, gamma: float, lam: float) -> np.ndarray:
    """Generalised advantage estimates of one episode that ended (no bootstrap beyond its last step)."""
    adv = np.zeros_like(rewards, dtype=np.float64)
    acc = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        nxt = values[t + 1] if t + 1 < len(values) else 0.0
        acc = rewards[t] + gamma * nxt - values[t] + gamma * lam * acc
        adv[t] = acc
    return adv


class RecurrentPPO:
    """The state of the PPO stage: the actor (the student's network), its log std, the critic, one optimiser."""

    def __init__(self, net, columns: np.ndarray, obs_dim: int, config: Any) -> None:
        import torch

        self.net, self.columns, self.config = net, columns, config
        self.log_std = torch.nn.Parameter(torch.full((2,), float(config.ppo_log_std_init)))
        self.critic = make_critic(obs_dim, config.ppo_critic_hidden)
        params = [*net.parameters(), self.log_std, *self.critic.parameters()]
        self.optimiser = torch.optim.Adam(params, lr=config.ppo_learning_rate)
        self.return_scale = None  # the first wave's return std: the critic learns returns in that unit
        self.actor = StudentPolicy(net, columns)  # (its memory per batch slot while it acts)

    # ---- acting -----------------------------------------------------------------------------------------------------

    def reset(self, batch: int) -> None:
        self.actor.reset([{}] * batch)

    def sample(self, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The Gaussian actions of a batch of observations (the actor's memory carried); unclipped."""
        mean = self.actor.mean(obs)
        return (mean + np.exp(self.log_std.detach().numpy()) * rng.standard_normal(mean.shape)).astype(np.float32)

    # ---- learning ---------------------------------------------------------------------------------------------------

    def update(self, wave: Wave, bc_coef: float, rng: np.random.Generator) -> dict[str, Any]:
        """PPO epochs on one wave; returns the update's statistics."""
        import torch

        cfg = self.config
        n = len(wave.rewards)
        T = max(len(r) for r in wave.rewards)
        full = torch.from_numpy(pad_episodes(wave.obs, T))
        x = full[..., torch.as_tensor(self.columns)]
        a = torch.from_numpy(pad_episodes(wave.actions, T))
        y = torch.from_numpy(pad_episodes(wave.labels, T))
        mask = torch.from_numpy(pad_episodes([np.ones(len(r)) for r in wave.rewards], T))
        if self.return_scale is None:
            set_statistics(self.critic, np.concatenate(wave.obs))
            returns = [np.cumsum(r[::-1])[::-1] for r in wave.rewards]
            self.return_scale = float(np.std(np.concatenate(returns))) or 1.0
        with torch.no_grad():
            mean, _ = self.net(x)
            values = self.critic(full).numpy() * self.return_scale
            old_logp = self._logp(mean, a)
        adv = [gae(r, values[k, :len(r)], cfg.ppo_gamma, cfg.ppo_lam) for k, r in enumerate(wave.rewards)]
        ret = [adv[k] + values[k, :len(r)] for k, r in enumerate(wave.rewards)]
        flat = np.concatenate(adv)
        adv_t = torch.from_numpy(pad_episodes([(d - flat.mean()) / (flat.std() + 1e-8) for d in adv], T))
        ret_t = torch.from_numpy(pad_episodes([r / self.return_scale for r in ret], T))
        q = torch.tensor(cfg.quantiles, dtype=torch.float32)
        stats = {"policy_loss": [], "value_loss": [], "bc_loss": [], "clip_fraction": [], "kl": []}
        self.net.train()
        for _ in range(cfg.ppo_epochs):
            for idx in np.array_split(rng.permutation(n), max(1, n // cfg.ppo_minibatch_episodes)):
                k = torch.as_tensor(idx)
                m = mask[k]
                mean, _ = self.net(x[k])
                logp = self._logp(mean, a[k])
                ratio = torch.exp(logp - old_logp[k])
                surr = torch.minimum(ratio * adv_t[k], ratio.clamp(1 - cfg.ppo_clip, 1 + cfg.ppo_clip) * adv_t[k])
                steps = m.sum().clamp(min=1.0)
                policy_loss = -(surr * m).sum() / steps
                value_loss = (((self.critic(full[k]) - ret_t[k]) ** 2) * m).sum() / steps
                bc = pinball(mean, y[k], m, q) if bc_coef > 0 else torch.zeros(())
                loss = policy_loss + cfg.ppo_value_coef * value_loss + bc_coef * bc
                self.optimiser.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_([*self.net.parameters(), self.log_std, *self.critic.parameters()],
                                               cfg.ppo_max_grad_norm)
                self.optimiser.step()
                with torch.no_grad():
                    stats["policy_loss"].append(policy_loss.item())
                    stats["value_loss"].append(value_loss.item())
                    stats["bc_loss"].append(bc.item())
                    stats["clip_fraction"].append(float((((ratio - 1).abs() > cfg.ppo_clip).float() * m).sum()
                                                        / steps))
                    stats["kl"].append(float((((old_logp[k] - logp) * m).sum() / steps)))
        self.net.eval()
        out = {key: float(np.mean(v)) for key, v in stats.items()}
        out["action_std"] = [float(v) for v in np.exp(self.log_std.detach().numpy())]
        out["mean_return"] = float(np.mean([r.sum() for r in wave.rewards]))
        return out

    def _logp(self, mean, actions):
        import torch

        std = torch.exp(self.log_std)
        return (-0.5 * ((actions - mean) / std) ** 2 - self.log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
