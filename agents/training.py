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

``--resume DIR`` continues from the newest checkpoint (or final model) in DIR with the config saved
there; the step count continues (SB3 ``reset_num_timesteps=False``).
"""

from __future__ import annotations

import json
import re
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import (
    ConfigError,
    atomic_write,
    builtin_config,
    check_choice,
    from_dict,
    read_yaml,
    to_dict,
    write_yaml,
)

ALGOS = ("ppo", "sac")


@dataclass(frozen=True)
class TrainConfig:
    """A training run (hyper-parameters are passed to the SB3 algorithm as given).

    These defaults ARE the default run: ``configs/train/ppo.yaml`` spells the same values out (a test
    checks that both agree), so ``msdgrasp train`` with or without ``--config configs/train/ppo.yaml``
    trains the same thing.
    """

    algo: str = "ppo"
    total_timesteps: int = 350_000
    n_envs: int = 16
    seed: int = 0
    checkpoint_every: int = 25_000
    torch_threads: int = 1
    policy_net: tuple[int, ...] = (64, 64)
    #: behaviour-cloning warm start: a controller spec ('reactive', 'fixed', ...) whose actions the policy
    #: imitates before RL. None (the default): PPO learns from scratch.
    bc_teacher: str | None = None
    #: environment steps of teacher demonstrations
    bc_steps: int = 32_768
    bc_epochs: int = 40
    #: log standard deviation of the policy's action noise after cloning (exploration around the teacher)
    bc_log_std: float = -1.2
    #: also fit the critic to the teacher's discounted returns during cloning (see :func:`behaviour_clone`)
    bc_value_fit: bool = False
    #: model selection: at every checkpoint and at the end the policy runs ``validation_episodes`` episodes
    #: at each friction in ``validation_mu`` (seeds disjoint from ``msdgrasp evaluate``'s); the best (highest
    #: success rate, then lowest mean peak pinch) is kept as ``best_model.zip``. 0 disables it.
    validation_episodes: int = 6
    validation_mu: tuple[float, ...] = (0.2, 0.3, 0.5, 0.7, 0.9)
    #: learning-rate schedule: "constant", or "linear" (from the algorithm's learning_rate down to 0 at
    #: total_timesteps; a resumed run anneals over the steps that remain)
    lr_schedule: str = "constant"
    #: PPO only: the critic also sees the privileged entries of the observation (mu, stiffness and mass
    #: scales, node displacements); the actor does not (agents/networks.py). Needs env.privileged_obs.
    asymmetric_critic: bool = False
    ppo: dict = field(default_factory=lambda: {
        "learning_rate": 1e-3, "n_steps": 256, "batch_size": 1024, "n_epochs": 10, "gamma": 0.995,
        "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
    })
    sac: dict = field(default_factory=lambda: {
        "learning_rate": 3e-4, "buffer_size": 200_000, "batch_size": 256, "gamma": 0.99, "tau": 0.005,
        "learning_starts": 2000, "train_freq": 1, "gradient_steps": 1,
    })
    env: GraspLiftConfig = field(default_factory=GraspLiftConfig)

    def __post_init__(self) -> None:
        check_choice("algo", self.algo, ALGOS)
        check_choice("lr_schedule", self.lr_schedule, ("constant", "linear"))
        if not isinstance(self.asymmetric_critic, bool):
            raise ConfigError(f"asymmetric_critic must be true or false, got {self.asymmetric_critic!r}")
        if self.asymmetric_critic and self.algo != "ppo":
            raise ConfigError(f"asymmetric_critic is implemented for algo 'ppo' only, got algo {self.algo!r}")
        if self.asymmetric_critic and not self.env.privileged_obs:
            raise ConfigError("asymmetric_critic: true needs env.privileged_obs: true (the critic's extra inputs)")
        for name, lo in (("total_timesteps", 1), ("n_envs", 1), ("checkpoint_every", 1), ("torch_threads", 1),
                         ("bc_steps", 1), ("bc_epochs", 0), ("validation_episodes", 0)):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int) or val < lo:
                raise ConfigError(f"{name} must be an integer >= {lo}, got {val!r}")
        mus = self.validation_mu
        if (not isinstance(mus, (tuple, list)) or not mus
                or any(isinstance(m, bool) or not isinstance(m, (int, float)) or not 0.0 <= m <= 2.0 for m in mus)):
            raise ConfigError(f"validation_mu must be a non-empty list of friction coefficients in [0, 2], got {mus!r}")
        object.__setattr__(self, "validation_mu", tuple(float(m) for m in mus))
        if not isinstance(self.bc_value_fit, bool):
            raise ConfigError(f"bc_value_fit must be true or false, got {self.bc_value_fit!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise ConfigError(f"seed must be an integer, got {self.seed!r}")
        if not self.policy_net or any((not isinstance(h, int)) or h < 1 for h in self.policy_net):
            raise ConfigError(f"policy_net must be a list of positive layer widths, got {self.policy_net!r}")
        for name in ALGOS:  # a typo in a hyper-parameter block fails here, before a run folder is made
            block = getattr(self, name)
            if not isinstance(block, dict):
                raise ConfigError(f"{name} must be a mapping of {name.upper()} keyword arguments, got {block!r}")
            unknown = sorted(set(block) - _algo_parameters(name))
            if unknown:
                raise ConfigError(f"{name}: unknown {name.upper()} argument(s) {unknown}; allowed: "
                                  f"{sorted(_algo_parameters(name))}")

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        return from_dict(cls, read_yaml(path), where=Path(path).name)


#: arguments of the algorithms' constructors that the training run sets itself (not configurable)
_RESERVED = {"self", "policy", "env", "seed", "device", "verbose", "tensorboard_log", "policy_kwargs", "_init_setup_model"}


def _algo_parameters(name: str) -> set[str]:
    import inspect

    return set(inspect.signature(_algo_class(name).__init__).parameters) - _RESERVED


def _algo_class(name: str):
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[name]


def model_config_path(path: str | Path) -> Path | None:
    """The training config saved with a model: ``<model>.yaml`` or the run folder's ``config.yaml``."""
    path = Path(path)
    for cfg in (path.with_suffix(".yaml"), path.parent / "config.yaml", path.parent.parent / "config.yaml"):
        if cfg.is_file():
            return cfg
    return None


def model_train_config(path: str | Path) -> TrainConfig | None:
    """The :class:`TrainConfig` a saved model was trained with (None: no config saved with it). A config
    that is there but broken is an error, never skipped."""
    cfg = model_config_path(path)
    if cfg is None:
        return None
    try:
        return TrainConfig.load(cfg)
    except ConfigError as exc:
        raise ConfigError(f"model {path}: its training config {cfg} is invalid: {exc}") from None


def load_model(path: str | Path, env=None):
    """Load a saved model; its algorithm comes from the config saved next to it (without one: PPO, then SAC)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ConfigError(f"model file {path} is not a Stable-Baselines3 .zip archive (corrupt or wrong file)")
    saved = model_train_config(path)
    algos = [saved.algo] if saved is not None else list(ALGOS)
    errors = []
    for name in algos:
        try:
            return _algo_class(name).load(path, env=env, device="cpu")
        except Exception as exc:  # noqa: BLE001 - SB3 raises many kinds on a bad archive
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
    raise ConfigError(f"cannot load model {path}: " + "; ".join(errors))


def _save_atomic(model, path: Path) -> Path:
    return atomic_write(path, lambda p: model.save(p))


def _latest_model(run_dir: Path) -> tuple[Path, int]:
    ckpts = []
    for p in (run_dir / "checkpoints").glob("model_*.zip"):
        m = re.fullmatch(r"model_(\d+)\.zip", p.name)
        if m:
            ckpts.append((int(m.group(1)), p))
    if ckpts:
        steps, p = max(ckpts)
        return p, steps
    final = run_dir / "final_model.zip"
    if final.is_file():
        return final, -1
    raise ConfigError(f"--resume {run_dir}: no checkpoints/model_<steps>.zip or final_model.zip to resume from")


def train(config: TrainConfig, out_dir: str | Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Train (or resume) and return a summary; all outputs in ``out_dir`` (see module docstring)."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    from ..envs.sb3 import GraspLiftSB3VecEnv

    out = Path(out_dir)
    torch.set_num_threads(config.torch_threads)
    write_yaml(out / "config.yaml", to_dict(config))
    venv = GraspLiftSB3VecEnv(config.n_envs, config.env, seed=config.seed)
    algo_cls = _algo_class(config.algo)
    if resume:
        path, _ = _latest_model(out)
        model = algo_cls.load(path, env=venv, device="cpu", tensorboard_log=str(out / "tb"))
    else:
        kwargs = dict(config.ppo if config.algo == "ppo" else config.sac)
        if config.lr_schedule == "linear":
            from stable_baselines3.common.utils import LinearSchedule

            kwargs["learning_rate"] = LinearSchedule(float(kwargs.get("learning_rate", 3e-4)), 0.0, 1.0)
        policy, policy_kwargs = "MlpPolicy", {"net_arch": list(config.policy_net)}
        if config.asymmetric_critic:
            from ..envs.core import OBS_NAMES
            from .networks import AsymmetricActorCriticPolicy, actor_mask

            core = venv.core
            policy = AsymmetricActorCriticPolicy
            policy_kwargs["actor_mask"] = actor_mask(len(OBS_NAMES), core.frame_dim, config.env.obs_history)
        model = algo_cls(
            policy, venv, seed=config.seed, device="cpu", verbose=0, tensorboard_log=str(out / "tb"),
            policy_kwargs=policy_kwargs, **kwargs,
        )

    selector = BestModel(config, out, resume=resume)

    class Checkpoint(BaseCallback):
        def __init__(self, every: int):
            super().__init__()
            self.every = every
            self.next = (model.num_timesteps // every + 1) * every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                path = _save_atomic(self.model, out / "checkpoints" / f"model_{self.num_timesteps}.zip")
                selector.consider(self.model, path)
                self.next += self.every
            return True

    bc = None
    if not resume and config.bc_teacher and config.algo == "ppo":
        bc = behaviour_clone(model, config)
    start_steps = model.num_timesteps
    remaining = config.total_timesteps - start_steps
    t0 = time.perf_counter()
    if remaining > 0:
        model.learn(
            remaining, callback=Checkpoint(config.checkpoint_every), progress_bar=progress,
            reset_num_timesteps=not resume, tb_log_name="run",
        )
    wall = time.perf_counter() - t0
    final = _save_atomic(model, out / "final_model.zip")
    write_yaml(out / "final_model.yaml", to_dict(config))
    selector.consider(model, final)
    succ = list(model.ep_success_buffer) if model.ep_success_buffer is not None else []
    summary = {
        "algo": config.algo,
        "timesteps": int(model.num_timesteps),
        "resumed_from": int(start_steps) if resume else None,
        "wall_time_s": round(wall, 1),
        "steps_per_s": round((model.num_timesteps - start_steps) / wall, 1) if wall > 0 else None,
        "recent_success_rate": round(sum(succ) / len(succ), 3) if succ else None,
        "behaviour_cloning": bc,
        "final_model": str(final),
        "best_model": str(out / "best_model.zip") if selector.best else None,
        "best_validation": selector.best,
    }
    atomic_write(out / "train_summary.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    venv.close()
    return summary


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


#: validation episodes are seeded from seed + this: disjoint from ``msdgrasp evaluate``'s seeds 0, 1, ...
VALIDATION_SEED_OFFSET = 100_000


class BestModel:
    """Scores saved models on validation episodes and keeps the best as ``best_model.zip``.

    PPO is not monotonic (a run's validation success can dip between checkpoints while it trades force
    against slip), so the last model is not necessarily the one to ship. The key is the success rate,
    then the lower mean peak pinch. The history goes to ``validation.json`` (atomic), which a resumed run
    reads back, and is the learning curve of ``msdgrasp train --seeds``.
    """

    def __init__(self, config: TrainConfig, out: Path, resume: bool = False) -> None:
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

    @staticmethod
    def _key(rec: dict[str, Any]) -> tuple[float, float]:
        return (rec["success_rate"], -rec["mean_peak_pinch_N"])

    def consider(self, model, path: Path) -> dict[str, Any] | None:
        """Validate ``model`` (saved at ``path``); copy it to best_model.zip if it beats the best so far."""
        cfg = self.config
        if cfg.validation_episodes == 0:
            return None
        from .controllers import ModelPolicy
        from .evaluation import evaluate_policy

        rows = evaluate_policy(ModelPolicy.from_model(model, "validation"), cfg.validation_mu, cfg.validation_episodes,
                               cfg.env, seed=cfg.seed + VALIDATION_SEED_OFFSET, _envs=self._envs)
        rec = {
            "timesteps": int(model.num_timesteps),
            "model": str(path),
            "success_rate": round(float(np.mean([r["success_rate"] for r in rows])), 4),
            "mean_peak_pinch_N": round(float(np.mean([r["mean_peak_pinch_N"] for r in rows])), 4),
            "success_by_mu": {f"{r['mu']:g}": r["success_rate"] for r in rows},
        }
        self.history.append(rec)
        if self.best is None or self._key(rec) > self._key(self.best):
            self.best = rec
            _save_atomic(model, self.out / "best_model.zip")
            write_yaml(self.out / "best_model.yaml", to_dict(cfg))
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
    from .controllers import make_policy

    env = GraspLiftVectorEnv(config.n_envs, config.env)
    teacher = make_policy(config.bc_teacher, config.env)
    obs, info = env.reset(seed=config.seed + 10_000)
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
    import torch

    demos = collect_demonstrations(config)
    policy = model.policy
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    x = torch.as_tensor(demos.obs, dtype=torch.float32)
    y = torch.as_tensor(demos.actions, dtype=torch.float32)
    known = np.isfinite(demos.returns)
    xv = x[torch.as_tensor(known)]
    v = torch.as_tensor(demos.returns[known], dtype=torch.float32)
    fit_value = config.bc_value_fit and len(v) > 0
    n = len(x)
    if fit_value:
        with torch.no_grad():  # start the critic at the mean return: Adam then only fits the variation
            policy.value_net.bias.fill_(float(v.mean()))
    gen = torch.Generator().manual_seed(config.seed)
    loss_val = float("nan")
    vloss_val = float("nan")
    for _ in range(config.bc_epochs):
        perm = torch.randperm(n, generator=gen)
        vperm = torch.randperm(len(v), generator=gen) if fit_value else None
        for j, k in enumerate(range(0, n, 512)):
            idx = perm[k : k + 512]
            mean = policy.get_distribution(x[idx]).distribution.mean
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
        policy.log_std.fill_(config.bc_log_std)
    out = {"demo_steps": int(n), "final_mse": round(loss_val, 5)}
    if fit_value:
        out["value_fit_steps"] = int(len(v))
        out["value_final_mse"] = round(vloss_val, 4)
        out["return_std"] = round(float(v.std()), 3)
    return out


def train_cli(args) -> int:
    if args.resume is not None:
        if args.seeds is not None:
            raise ConfigError("--resume continues one run; it cannot be combined with --seeds")
        run_dir = Path(args.resume)
        if not (run_dir / "config.yaml").is_file():
            raise ConfigError(f"--resume {run_dir}: no config.yaml there (not a training run folder)")
        config = TrainConfig.load(run_dir / "config.yaml")
        overrides = {"total_timesteps": args.total_timesteps} if args.total_timesteps else {}
        if overrides:
            config = from_dict(TrainConfig, {**to_dict(config), **overrides})
        summary = train(config, run_dir, resume=True, progress=not args.quiet)
    else:
        path = args.config or builtin_config("train/ppo.yaml")
        data = read_yaml(path)
        for key, val in (("algo", args.algo), ("total_timesteps", args.total_timesteps), ("n_envs", args.n_envs),
                         ("seed", args.seed)):
            if val is not None:
                data[key] = val
        config = from_dict(TrainConfig, data, where=Path(path).name)
        if args.seeds is not None:
            from .seeds import parse_seeds, run_seeds

            if args.seed is not None:
                raise ConfigError("give either --seed or --seeds, not both")
            seeds = parse_seeds(args.seeds)
            result = run_seeds(config, seeds, args.out, workers=args.workers, progress=not args.quiet)
            print(json.dumps({"files": result["files"], "aggregate": result["aggregate"]}, indent=2))
            return 0
        summary = train(config, args.out, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0
