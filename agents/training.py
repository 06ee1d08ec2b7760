"""Train grasp policies with Stable-Baselines3 on the natively batched GraspLift env.

``msdgrasp train`` reads ``configs/train/ppo.yaml`` (or ``--config``), trains on
:class:`~msdgrasp.envs.sb3.GraspLiftSB3VecEnv` (all envs in one numba call per step), and writes into
``--out``:

* ``config.yaml``: the exact, fully resolved training config (written first);
* ``checkpoints/model_<steps>.zip``: periodic checkpoints (atomic writes);
* ``final_model.zip`` + ``final_model.yaml`` (the config again, next to the model);
* ``best_model.zip`` + ``best_model.yaml``: the checkpoint that did best on the validation episodes
  (:class:`BestModel`), with the scores of every checkpoint in ``validation.json``; this is the model to
  evaluate and deploy;
* ``tb/``: TensorBoard logs.

With ``validation_patience`` set (the default run's 3), the run ends once that many validations in a row have not
beaten the best; ``train_summary.json``'s ``stopped_early`` says where.

``--resume DIR`` continues from the newest checkpoint (or final model) in DIR with the config saved
there; the step count continues (SB3 ``reset_num_timesteps=False``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..physics.config import ConfigError, atomic_write, needs_extra, to_dict, write_yaml
from .learners.base import numbered_files
from .learners.sb3_layout import FINAL_MODEL, LAYOUT, algo_class, is_ppo, load_model, model_config_path  # noqa: F401
from .learners.sb3_layout import model_train_config  # noqa: F401 (re-exported)
from .models import TrainConfig
from .controllers import make_policy
from .model_policy import ModelPolicy
from .evaluation import evaluate_policy
# validation episodes are seeded from seed + VALIDATION_SEED_OFFSET (re-exported), far below the sealed evaluation
# seeds that ``msdgrasp evaluate`` draws from (agents/protocol.py)
from .protocol import DEMONSTRATION_SEED_OFFSET, VALIDATION_SEED_OFFSET, check_not_sealed
from .stats import wilson_lower_bound
from .residual import residual_venv, with_residual


def _save_atomic(model, path: Path) -> Path:
    return atomic_write(path, lambda p: model.save(p))


def _latest_model(run_dir: Path) -> tuple[Path, int]:
    ckpts = numbered_files(run_dir, LAYOUT.checkpoint)
    if ckpts:
        steps, p = max(ckpts)
        return p, steps
    final = run_dir / FINAL_MODEL
    if final.is_file():
        return final, -1
    raise ConfigError(f"--resume {run_dir}: no {LAYOUT.checkpoint.format('<steps>')} or {FINAL_MODEL} to resume from")


def train(config: TrainConfig, out_dir: str | Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) and return a summary; all outputs in ``out_dir`` (see module docstring)."""
    with needs_extra("train", "training"):
        import torch
        from stable_baselines3.common.callbacks import BaseCallback

    from ..envs.sb3 import GraspLiftSB3VecEnv

    out = Path(out_dir)
    if not resume:
        config.check_inputs()
    torch.set_num_threads(config.torch_threads)
    write_yaml(out / LAYOUT.config, to_dict(config))
    # (built on the widest randomisation it will draw from: the curriculum's end)
    venv = residual_venv(GraspLiftSB3VecEnv(config.n_envs, config.training_task(), seed=config.seed,
                                            precision=config.precision), config)
    if resume:
        path, _ = _latest_model(out)
        model = algo_class(config.algo).load(path, env=venv, device="cpu", tensorboard_log=str(out / "tb"))
    else:
        model = new_model(config, venv, tensorboard_log=str(out / "tb"))
        if config.init_model is not None:
            warm_start(model, config.init_model_path())

    selector = BestModel(config, out, resume=resume)

    class Checkpoint(BaseCallback):
        def __init__(self, every: int):
            super().__init__()
            self.every = every
            self.next = (model.num_timesteps // every + 1) * every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                path = _save_atomic(self.model, out / LAYOUT.checkpoint.format(self.num_timesteps))
                selector.consider(self.model, path)
                self.next += self.every
                # (False ends model.learn here, before this rollout's update: the final model is this checkpoint)
                return not selector.patience_spent()
            return True

    def follow_ramp() -> None:  # the env's randomisation where config.randomization_ramp is at this step count
        task = config.training_task(model.num_timesteps / config.total_timesteps)
        if task.randomization != venv.core.config.randomization:
            venv.core.set_randomization(task.randomization)

    class Curriculum(BaseCallback):
        def _on_rollout_start(self) -> None:
            follow_ramp()

        def _on_step(self) -> bool:
            return True

    callbacks = [Checkpoint(config.checkpoint_every)]
    if config.randomization_ramp is not None:
        callbacks.append(Curriculum())
        follow_ramp()  # (before the first reset)

    bc = None
    if not resume and config.bc_teacher and is_ppo(config.algo):
        bc = behaviour_clone(model, config)
    start_steps = model.num_timesteps
    remaining = config.total_timesteps - start_steps
    t0 = time.perf_counter()
    if remaining > 0 and not selector.patience_spent():  # (a resumed run that had stopped early stays stopped)
        model.learn(
            remaining, callback=callbacks, progress_bar=progress,
            reset_num_timesteps=not resume, tb_log_name="run",
        )
    wall = time.perf_counter() - t0
    stopped_early = selector.patience_spent()
    final = _save_atomic(model, out / FINAL_MODEL)
    write_yaml(final.with_suffix(".yaml"), to_dict(config))
    if not stopped_early:  # (stopped early, the final model is the checkpoint validated last)
        selector.consider(model, final)
    succ = list(model.ep_success_buffer) if model.ep_success_buffer is not None else []
    summary = {
        "algo": config.algo,
        "precision": venv.core.precision,
        "timesteps": int(model.num_timesteps),
        "resumed_from": int(start_steps) if resume else None,
        "wall_time_s": round(wall, 1),
        "steps_per_s": round((model.num_timesteps - start_steps) / wall, 1) if wall > 0 else None,
        "recent_success_rate": round(sum(succ) / len(succ), 3) if succ else None,
        "behaviour_cloning": bc,
        "final_model": str(final),
        "best_model": str(out / LAYOUT.model) if selector.best else None,
        "best_validation": selector.best,
        # early stopping (validation_patience): where the run ended; None: it ran to total_timesteps
        "stopped_early": ({"timesteps": int(model.num_timesteps), "validation_patience": config.validation_patience}
                          if stopped_early else None),
    }
    atomic_write(out / LAYOUT.summary, lambda p: p.write_text(json.dumps(summary, indent=2)))
    venv.close()
    return summary


def new_model(config: TrainConfig, venv, tensorboard_log: str | None = None):
    """A fresh SB3 model of ``config`` (its algorithm, network, action squashing, asymmetric critic) on ``venv``
    (a :class:`~msdgrasp.envs.sb3.GraspLiftSB3VecEnv` of the config's task)."""
    kwargs = dict(getattr(config, config.algo))  # (the config's block of the algorithm: ppo or sac)
    if config.lr_schedule == "linear":
        from stable_baselines3.common.utils import LinearSchedule

        kwargs["learning_rate"] = LinearSchedule(float(kwargs.get("learning_rate", 3e-4)), 0.0, 1.0)
    policy, policy_kwargs = "MlpPolicy", {"net_arch": list(config.policy_net)}
    if is_ppo(config.algo):
        policy_kwargs["log_std_init"] = float(config.log_std_init)
        if config.squash_actions:
            policy_kwargs["squash_output"] = True
    if config.asymmetric_critic:
        from ..envs.core import OBS_NAMES, actor_mask
        from .networks import AsymmetricActorCriticPolicy

        policy = AsymmetricActorCriticPolicy
        policy_kwargs["actor_mask"] = actor_mask(len(OBS_NAMES), venv.core.frame_dim, config.env.obs_history,
                                                 config.actor_hidden, config.actor_privileged,
                                                 config.env.privileged_perturbations)
    return algo_class(config.algo)(
        policy, venv, seed=config.seed, device="cpu", verbose=0, tensorboard_log=tensorboard_log,
        policy_kwargs=policy_kwargs, **kwargs,
    )


def warm_start(model, path: Path) -> None:
    """Copy the weights of the trained model at ``path`` (actor, critic, action noise) into ``model``.

    Only the network is taken: the optimiser's moments, the step count and the learning-rate schedule are
    ``model``'s own, so a warm-started run is a fresh run from those weights. The saved model must have the
    same observation and action spaces and the same network (a one-line error names what differs).
    """
    from stable_baselines3.common.save_util import load_from_zip_file

    data, params, _ = load_from_zip_file(path, device="cpu")
    for name in ("observation_space", "action_space"):
        saved, ours = data.get(name), getattr(model, name)
        if saved is None or saved.shape != ours.shape:
            raise ConfigError(f"init_model: {path} was trained with {name} of shape "
                              f"{getattr(saved, 'shape', None)}, this run's is {ours.shape} (the task's "
                              "observation or action layout differs)")
    try:
        model.policy.load_state_dict(params["policy"])
    except (KeyError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0]
        raise ConfigError(f"init_model: {path}'s network does not match this run's policy_net / critic "
                          f"({first})") from None


class Demonstrations(NamedTuple):
    """Teacher rollouts: one row per (env step, sub-env)."""

    obs: np.ndarray
    actions: np.ndarray
    #: discounted return from each step to the end of its episode (NaN: the episode was still running
    #: when collection stopped, so its return is unknown)
    returns: np.ndarray


def _discounted_returns(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """Per-step discounted returns of (T, B) rewards; NaN after the last episode end of each column."""
    ret = np.full(rewards.shape, np.nan)
    acc = np.full(rewards.shape[1], np.nan)  # NaN until a finished episode is seen (going backwards)
    for t in range(len(rewards) - 1, -1, -1):
        acc = np.where(dones[t], 0.0, acc)
        acc = rewards[t] + gamma * acc
        ret[t] = acc
    return ret


class BestModel:
    """Scores saved models on validation episodes and keeps the best as ``best_model.zip``.

    PPO is not monotonic (a run's validation success can dip between checkpoints while it trades force
    against slip), so the last model is not necessarily the one to ship. The key is the success rate,
    then the lower force cost: the mean over the validation mu of the peak pinch weighted as the reward
    charges it (by mu / ``env.reward.peak_force_mu_ref`` when that is set, else the plain mean peak
    pinch), so selection and training agree on what "less force" means. The history goes to
    ``validation.json`` (atomic), which a resumed run reads back, and is the learning curve of
    ``msdgrasp train --seeds``.
    """

    def __init__(self, config: TrainConfig, out: Path, resume: bool = False) -> None:
        # (config: any learner's config with seed, env and validation_episodes / validation_mu: SB3's
        # TrainConfig or the torch PPO's TorchPPOConfig)
        self.config = config
        self.out = out
        self.history: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None
        self._envs: dict = {}
        log = out / "validation.json"
        if resume and log.is_file():
            try:
                data = json.loads(log.read_text())
                self.history, self.best = list(data["history"]), data["best"]
            except (ValueError, KeyError, TypeError) as exc:
                raise ConfigError(f"--resume: {log} is corrupt ({exc}); delete it to restart model selection") from None

    def patience_spent(self) -> bool:
        """Early stopping's rule: whether the last ``config.validation_patience`` validations (where it is set) have
        none of them beaten the best one. Read from the history, so a resumed run keeps it."""
        patience = getattr(self.config, "validation_patience", None)
        if patience is None or self.best is None:
            return False
        since_best = len(self.history) - 1 - max(k for k, rec in enumerate(self.history) if rec == self.best)
        return since_best >= patience

    def _key(self, rec: dict[str, Any]) -> tuple[float, ...]:
        # records of runs made before force_cost_N existed carry only the plain mean
        force = -rec.get("force_cost_N", rec["mean_peak_pinch_N"])
        if getattr(self.config, "selection", "success") == "grasps":
            # success as a constraint: the lowest Wilson lower bound over mu first, so that no checkpoint trades a
            # low-friction grasp for force; then the mean success, then force
            n = self.config.validation_episodes
            lowest = min(wilson_lower_bound(round(rate * n), n) for rate in rec["success_by_mu"].values())
            return (round(lowest, 9), rec["success_rate"], force)
        return (rec["success_rate"], force)

    def force_cost(self, rows: list[dict[str, Any]]) -> float:
        """Mean peak pinch (N) over the validation rows, weighted per mu as the reward charges it."""
        weight = self.config.env.reward.peak_force_weight
        return float(np.mean([r["mean_peak_pinch_N"] * weight(r["mu"]) for r in rows]))

    def consider(self, model, path: Path) -> dict[str, Any] | None:
        """Validate the SB3 ``model`` (saved at ``path``); copy it to best_model.zip if it beats the best so far."""

        def keep() -> None:
            best = _save_atomic(model, self.out / LAYOUT.model)
            write_yaml(best.with_suffix(".yaml"), to_dict(self.config))

        policy = with_residual(ModelPolicy.from_model(model, "validation"), self.config)
        return self.consider_policy(policy, int(model.num_timesteps), path, keep)

    def consider_policy(self, policy, timesteps: int, path: Path, keep: Callable[[], None]) -> dict[str, Any] | None:
        """Validate ``policy`` (saved at ``path`` after ``timesteps`` agent steps); call ``keep()`` if it beats
        the best so far (the learner saves it as its best). Any learner's policy: SB3's or the torch PPO's."""
        cfg = self.config
        if cfg.validation_episodes == 0:
            return None

        # (on the task the training draws from, at its full randomisation; never on the sealed evaluation seeds)
        check_not_sealed(cfg.seed + VALIDATION_SEED_OFFSET, cfg.validation_episodes, "seed", value=cfg.seed,
                         via=f"validation episodes: seed + {VALIDATION_SEED_OFFSET} + i")
        rows = evaluate_policy(policy, cfg.validation_mu, cfg.validation_episodes, cfg.training_task(),
                               seed=cfg.seed + VALIDATION_SEED_OFFSET, _envs=self._envs)
        rec = {
            "timesteps": int(timesteps),
            "model": str(path),
            "success_rate": round(float(np.mean([r["success_rate"] for r in rows])), 4),
            "mean_peak_pinch_N": round(float(np.mean([r["mean_peak_pinch_N"] for r in rows])), 4),
            "force_cost_N": round(self.force_cost(rows), 4),
            "success_by_mu": {f"{r['mu']:g}": r["success_rate"] for r in rows},
            "peak_pinch_by_mu": {f"{r['mu']:g}": round(r["mean_peak_pinch_N"], 4) for r in rows},
        }
        self.history.append(rec)
        if self.best is None or self._key(rec) > self._key(self.best):
            self.best = rec
            keep()
        data = {"validation_mu": list(cfg.validation_mu), "episodes_per_mu": cfg.validation_episodes,
                "best": self.best, "history": self.history}
        atomic_write(self.out / "validation.json", lambda p: p.write_text(json.dumps(data, indent=2)))
        return rec


def collect_demonstrations(config: TrainConfig) -> Demonstrations:
    """Teacher rollouts on randomised episodes of the batched env (observations, actions, returns).

    Returns are discounted with the PPO ``gamma`` (0.99 if unset); episodes ended by the time limit count
    as ended (the tail beyond the limit is not bootstrapped).
    """
    from ..envs.grasp_lift import GraspLiftVectorEnv

    env = GraspLiftVectorEnv(config.n_envs, config.env)
    teacher = make_policy(config.bc_teacher, config.env)
    obs, info = env.reset(seed=config.seed + DEMONSTRATION_SEED_OFFSET)
    teacher.reset([{"mu": m} for m in env.core.mu])
    xs, ys, rs, ds = [], [], [], []
    for _ in range(max(1, config.bc_steps // config.n_envs)):
        act = teacher.act(obs)
        xs.append(obs.copy())
        ys.append(act.copy())
        obs, rew, term, trunc, _ = env.core.step(act)
        done = term | trunc
        rs.append(np.asarray(rew, dtype=np.float64))
        ds.append(done)
        for i in np.flatnonzero(done):
            env.core.reset(i)
            teacher.reset_one(i, {"mu": float(env.core.mu[i])})
        obs = env.core.obs.astype(np.float32)
    gamma = float(config.ppo.get("gamma", 0.99))
    returns = _discounted_returns(np.stack(rs), np.stack(ds), gamma)
    return Demonstrations(np.concatenate(xs), np.concatenate(ys), returns.reshape(-1))


def behaviour_clone(model, config: TrainConfig) -> dict[str, float]:
    """Fit the PPO policy's mean action to teacher demonstrations (MSE), then set its action noise.

    With ``config.bc_value_fit`` the critic is fitted too, to the teacher's discounted returns (MSE), so
    that PPO's first advantages are not computed from an untrained value function: with a random critic
    the first updates are noise and drag the cloned policy away from the teacher (measured: the pinch
    force collapsed from 2.3 N to 1.3 N and low-friction success from 90 % to 0 % in the first 50k steps).
    """
    demos = collect_demonstrations(config)
    return fit_policy(model.policy, demos, config.bc_epochs, config.bc_log_std, seed=config.seed,
                      fit_value=config.bc_value_fit)


def fit_policy(policy, demos: Demonstrations, epochs: int, log_std: float, seed: int = 0,
               fit_value: bool = False) -> dict[str, float]:
    """Fit an SB3 PPO ``policy``'s mean action to ``demos`` (MSE over minibatches of 512, Adam 1e-3) for
    ``epochs`` passes, then set its log std to ``log_std``; with ``fit_value`` the critic too, to the demos'
    known returns. The one cloning step of online warm starts and of :mod:`.offline` datasets."""
    import torch

    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    x = torch.as_tensor(demos.obs, dtype=torch.float32)
    y = torch.as_tensor(demos.actions, dtype=torch.float32)
    known = np.isfinite(demos.returns)
    xv = x[torch.as_tensor(known)]
    v = torch.as_tensor(demos.returns[known], dtype=torch.float32)
    fit_value = fit_value and len(v) > 0
    n = len(x)
    if fit_value:
        with torch.no_grad():  # start the critic at the mean return: Adam then only fits the variation
            policy.value_net.bias.fill_(float(v.mean()))
    gen = torch.Generator().manual_seed(seed)
    loss_val = float("nan")
    vloss_val = float("nan")
    for _ in range(epochs):
        perm = torch.randperm(n, generator=gen)
        vperm = torch.randperm(len(v), generator=gen) if fit_value else None
        for j, k in enumerate(range(0, n, 512)):
            idx = perm[k : k + 512]
            mean = policy.get_distribution(x[idx]).distribution.mean
            if policy.squash_output:  # the action is tanh of the Gaussian's mean
                mean = torch.tanh(mean)
            loss = torch.mean((mean - y[idx]) ** 2)
            if fit_value:
                vidx = vperm[(j * 512) % len(v) :][:512]
                vloss = torch.mean((policy.predict_values(xv[vidx]).squeeze(-1) - v[vidx]) ** 2)
                loss = loss + vloss
                vloss_val = vloss.item()
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss_val = torch.mean((mean.detach() - y[idx]) ** 2).item()
    with torch.no_grad():
        policy.log_std.fill_(log_std)
    out = {"demo_steps": int(n), "final_mse": round(loss_val, 5)}
    if fit_value:
        out["value_fit_steps"] = int(len(v))
        out["value_final_mse"] = round(vloss_val, 4)
        out["return_std"] = round(float(v.std()), 3)
    return out
