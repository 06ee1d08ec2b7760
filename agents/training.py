"""Train grasp policies with Stable-Baselines3 on the natively batched GraspLift env.

``msdgrasp train`` reads ``configs/train/ppo.yaml`` (or ``--config``), trains on
:class:`~msdgrasp.envs.sb3.GraspLiftSB3VecEnv` (all envs in one numba call per step), and writes into
``--out``:

* ``config.yaml``: the exact, fully resolved training config (written first);
* ``checkpoints/model_<steps>.zip``: periodic checkpoints (atomic writes);
* ``final_model.zip`` + ``final_model.yaml`` (the config again, next to the model);
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
from typing import Any

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
    """A training run (hyper-parameters are passed to the SB3 algorithm as given)."""

    algo: str = "ppo"
    total_timesteps: int = 250_000
    n_envs: int = 16
    seed: int = 0
    checkpoint_every: int = 50_000
    torch_threads: int = 2
    policy_net: tuple[int, ...] = (64, 64)
    #: behaviour-cloning warm start: a controller spec ('reactive', 'fixed', ...) whose actions the policy
    #: imitates before RL (None: start from scratch). From scratch PPO settles on "never touch the
    #: tissue" (every touch costs force and slip penalties before any lift is earned).
    bc_teacher: str | None = "reactive"
    #: environment steps of teacher demonstrations
    bc_steps: int = 32_768
    bc_epochs: int = 40
    #: log standard deviation of the policy's action noise after cloning (exploration around the teacher)
    bc_log_std: float = -1.2
    ppo: dict = field(default_factory=lambda: {
        "learning_rate": 3e-4, "n_steps": 256, "batch_size": 1024, "n_epochs": 5, "gamma": 0.99,
        "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
    })
    sac: dict = field(default_factory=lambda: {
        "learning_rate": 3e-4, "buffer_size": 200_000, "batch_size": 256, "gamma": 0.99, "tau": 0.005,
        "learning_starts": 2000, "train_freq": 1, "gradient_steps": 1,
    })
    env: GraspLiftConfig = field(default_factory=GraspLiftConfig)

    def __post_init__(self) -> None:
        check_choice("algo", self.algo, ALGOS)
        for name, lo in (("total_timesteps", 1), ("n_envs", 1), ("checkpoint_every", 1), ("torch_threads", 1),
                         ("bc_steps", 1), ("bc_epochs", 0)):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int) or val < lo:
                raise ConfigError(f"{name} must be an integer >= {lo}, got {val!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise ConfigError(f"seed must be an integer, got {self.seed!r}")
        if not self.policy_net or any((not isinstance(h, int)) or h < 1 for h in self.policy_net):
            raise ConfigError(f"policy_net must be a list of positive layer widths, got {self.policy_net!r}")

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        return from_dict(cls, read_yaml(path), where=Path(path).name)


def _algo_class(name: str):
    from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[name]


def load_model(path: str | Path, env=None):
    """Load a saved model; its algorithm comes from the config saved next to it (else PPO, then SAC)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ConfigError(f"model file {path} is not a Stable-Baselines3 .zip archive (corrupt or wrong file)")
    algos = list(ALGOS)
    for cfg in (path.with_suffix(".yaml"), path.parent / "config.yaml", path.parent.parent / "config.yaml"):
        if cfg.is_file():
            try:
                algos = [TrainConfig.load(cfg).algo]
            except ConfigError:
                pass
            break
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
        model = algo_cls(
            "MlpPolicy", venv, seed=config.seed, device="cpu", verbose=0, tensorboard_log=str(out / "tb"),
            policy_kwargs={"net_arch": list(config.policy_net)}, **kwargs,
        )

    class Checkpoint(BaseCallback):
        def __init__(self, every: int):
            super().__init__()
            self.every = every
            self.next = (model.num_timesteps // every + 1) * every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                _save_atomic(self.model, out / "checkpoints" / f"model_{self.num_timesteps}.zip")
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
    }
    atomic_write(out / "train_summary.json", lambda p: p.write_text(json.dumps(summary, indent=2)))
    venv.close()
    return summary


def collect_demonstrations(config: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """(obs, actions) of the teacher controller on randomised episodes of the batched env."""
    from ..envs.grasp_lift import GraspLiftVectorEnv
    from .controllers import make_policy

    env = GraspLiftVectorEnv(config.n_envs, config.env)
    teacher = make_policy(config.bc_teacher, config.env)
    obs, info = env.reset(seed=config.seed + 10_000)
    teacher.reset([{"mu": m} for m in env.core.mu])
    xs, ys = [], []
    for _ in range(max(1, config.bc_steps // config.n_envs)):
        act = teacher.act(obs)
        xs.append(obs.copy())
        ys.append(act.copy())
        obs, _, term, trunc, _ = env.core.step(act)
        for i in np.flatnonzero(term | trunc):
            env.core.reset(i)
            teacher.reset_one(i, {"mu": float(env.core.mu[i])})
        obs = env.core.obs.astype(np.float32)
    return np.concatenate(xs), np.concatenate(ys)


def behaviour_clone(model, config: TrainConfig) -> dict[str, float]:
    """Fit the PPO policy's mean action to teacher demonstrations (MSE), then set its action noise."""
    import torch

    obs, act = collect_demonstrations(config)
    policy = model.policy
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    x = torch.as_tensor(obs, dtype=torch.float32)
    y = torch.as_tensor(act, dtype=torch.float32)
    n = len(x)
    gen = torch.Generator().manual_seed(config.seed)
    loss_val = float("nan")
    for _ in range(config.bc_epochs):
        perm = torch.randperm(n, generator=gen)
        for k in range(0, n, 512):
            idx = perm[k : k + 512]
            mean = policy.get_distribution(x[idx]).distribution.mean
            loss = torch.mean((mean - y[idx]) ** 2)
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss_val = loss.item()
    with torch.no_grad():
        policy.log_std.fill_(config.bc_log_std)
    return {"demo_steps": int(n), "final_mse": round(loss_val, 5)}


def train_cli(args) -> int:
    if args.resume is not None:
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
        summary = train(config, args.out, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0
