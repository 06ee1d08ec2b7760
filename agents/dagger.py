"""Teacher-student training (``msdgrasp train --learner dagger``): a student with memory learns, by DAgger, to act as a
privileged teacher acts, from what the grasper senses.

The teacher is told what no grasper senses: the episode's friction (``slipfeedback:...,told=1``: the estimating
controller with its estimate replaced by the true mu; it closes to the same probe grip, so the closing the student
sees is the one the friction shows in). The student (:mod:`.recurrent`) reads only the actor's sensed entries and must
infer from its history what the teacher is told. DAgger (Ross, Gordon and Bagnell 2011): in iteration 0 the teacher
drives (``teacher_drives`` of the episodes; then x ``beta_decay`` per iteration), afterwards the student drives; in every
step of every episode the teacher, run in the student's shadow on the same observations, labels what it would do, so
the data covers the states the student's own mistakes lead to. After each iteration the student is fitted on all
episodes so far (whole episodes, from a zero memory, as it runs), its checkpoint validated on the training task's
validation episodes and the best kept.

The loss is the pinball (quantile) loss per action: at ``quantiles[0]`` > 0.5 the student's grip is an upper quantile
of the teacher's grips over the frictions its history cannot tell apart (a grip too light loses the grasp; one too
heavy costs force), where a squared loss would grip at their mean. Selection (``selection: grasps``): the checkpoint
with the highest lowest Wilson bound of validation success over mu, then the least force: no checkpoint trades a
low-friction grasp for force (docs/design.md).
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import sys
import time
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from annotated_types import Ge, Le

from ..envs.core import OBS_NAMES, GraspLiftConfig, RandomizationConfig, actor_mask
from ..physics.config import (
    ConfigError, Int, Positive, Real, atomic_write, atomic_write_text, config_dataclass, from_dict, read_extending_yaml,
    replace, to_dict,
)
from .learners.dagger_layout import LAYOUT, NAME
from .models import default_training
from .protocol import VALIDATION_SEED_OFFSET, check_not_sealed
from .recurrent import MEMORIES, StudentPolicy, make_student_net, meta_path, save_student

Unit = Annotated[Real, Ge(0), Le(1)]
Quantile = Annotated[Real, Ge(0.05), Le(0.95)]

#: the default teacher: the estimating controller of the default training told the episode's mu
TEACHER = "slipfeedback:estimator=builtin,told=1,gate=0.9,gain=0.5,pull=0.3"


def _default_env() -> GraspLiftConfig:
    return default_training().env


def _default_randomization() -> RandomizationConfig:
    rnd = default_training().train_randomization
    assert rnd is not None  # (the default training draws its episodes from the robustness ranges)
    return rnd


@config_dataclass
class DaggerConfig:
    """One teacher-student run (``configs/train/dagger.yaml``); reasons for the values in docs/design.md."""

    #: the run's seed: the rollout envs (env i reset with seed + i), the drivers' draws and the networks
    seed: Annotated[Int, Ge(0)] = 0
    #: the privileged teacher, a controller spec told the episode's mu by its reset info
    teacher: str = TEACHER
    #: what the student remembers: "gru" (a recurrent state over the episode) or "none" (the current frame only)
    memory: Literal["gru", "none"] = "gru"
    #: width of the student's layers (input, GRU, head)
    hidden: Annotated[Int, Ge(4)] = 64
    #: DAgger iterations: each runs episodes_per_iteration episodes, then fits the student on all so far
    iterations: Annotated[Int, Ge(1)] = 6
    #: episodes per iteration, a multiple of n_envs (they run in waves of n_envs)
    episodes_per_iteration: Annotated[Int, Ge(1)] = 192
    #: envs run side by side in one batched env
    n_envs: Annotated[Int, Ge(1)] = 64
    #: share of iteration 0's episodes the teacher drives (the rest the student); later iterations: x beta_decay each
    teacher_drives: Unit = 1.0
    beta_decay: Unit = 0.0
    #: the quantile of the teacher's action the student's loss aims at, per action (jaw set-point, pull)
    quantiles: tuple[Quantile, Quantile] = (0.75, 0.5)
    #: Adam steps per iteration, each on batch_episodes whole episodes drawn from all data so far
    grad_steps: Annotated[Int, Ge(1)] = 250
    batch_episodes: Annotated[Int, Ge(1)] = 32
    learning_rate: Positive = 1e-3
    #: validation episodes per mu of every iteration's student (on the training task, seed + VALIDATION_SEED_OFFSET + i)
    validation_episodes: Annotated[Int, Ge(1)] = 24
    validation_mu: tuple[Annotated[Real, Ge(0)], ...] = (0.2, 0.3, 0.5, 0.8)
    #: how a checkpoint is picked: "grasps" (the lowest Wilson bound of success over mu, then force) or "success"
    #: (the mean success, then force: the SB3 training's rule)
    selection: Literal["grasps", "success"] = "grasps"
    #: the task the student acts on (the default training's: the benchmark task with a privileged block for teachers)
    env: GraspLiftConfig = field(default_factory=_default_env)
    #: the perturbations the episodes are drawn from (the default training's ranges)
    train_randomization: RandomizationConfig = field(default_factory=_default_randomization)

    @property
    def waves(self) -> int:
        """Waves of n_envs episodes per iteration."""
        return self.episodes_per_iteration // self.n_envs

    def seed_sets(self) -> list[tuple[int, int, str]]:
        """Every run of reset seeds the training derives from ``seed`` (first, count, how)."""
        n = self.iterations * self.waves * self.n_envs
        return [(self.seed, n, f"rollout episodes: seed + i, i < iterations x episodes_per_iteration = {n}"),
                (self.seed + VALIDATION_SEED_OFFSET, self.validation_episodes,
                 f"validation episodes: seed + {VALIDATION_SEED_OFFSET} + i, i < validation_episodes = "
                 f"{self.validation_episodes}")]

    def __post_init__(self) -> None:
        if self.episodes_per_iteration % self.n_envs:
            raise ConfigError(f"episodes_per_iteration must be a multiple of n_envs = {self.n_envs}, got "
                              f"{self.episodes_per_iteration}")
        if self.memory not in MEMORIES:
            raise ConfigError(f"memory must be one of {', '.join(MEMORIES)}, got {self.memory!r}")
        if not self.env.privileged_obs:
            raise ConfigError("env.privileged_obs must be true: the teacher reads the episode's mu")
        for first, count, via in self.seed_sets():  # (a training never draws the sealed evaluation episodes)
            check_not_sealed(first, count, "seed", value=self.seed, via=via)
        teacher_policy(self)  # (a bad teacher spec fails here, before anything runs)

    def training_task(self, progress: float = 1.0) -> GraspLiftConfig:
        """The task the episodes are drawn from (and the validation's): env with the training's perturbations."""
        return replace(self.env, randomization=self.train_randomization)

    @classmethod
    def load(cls, path: str | Path) -> "DaggerConfig":
        return from_dict(cls, read_extending_yaml(path), where=Path(path).name)


def teacher_policy(config: DaggerConfig):
    """The teacher of ``config`` (ConfigError naming the field where its spec is not a controller told mu)."""
    from .controllers import make_policy

    if not config.teacher.startswith("slipfeedback:") or "told=1" not in config.teacher.replace(" ", ""):
        raise ConfigError(f"teacher must be a slip-feedback controller told mu ('slipfeedback:...,told=1,...'), got "
                          f"{config.teacher!r}")
    try:
        return make_policy(config.teacher, config.env)
    except (ValueError, ConfigError) as exc:
        raise ConfigError(f"teacher: {exc}") from None


def student_columns(core) -> np.ndarray:
    """The observation entries of the task ``core`` the student sees: the sensed entries of every frame, never the
    privileged ones."""
    return np.flatnonzero(actor_mask(len(OBS_NAMES), core.frame_dim, core.config.obs_history))


def pinball(pred, target, mask, quantiles):
    """Mean pinball loss over the masked steps, per action its quantile (torch tensors (B, T, 2), (B, T), (2,))."""
    err = target - pred
    loss = (quantiles * err).maximum((quantiles - 1.0) * err)
    return (loss.sum(-1) * mask).sum() / mask.sum().clamp(min=1.0)


def _rollouts(env, student: StudentPolicy, teacher, columns: np.ndarray, drivers: np.ndarray,
              seeds: list[int]) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """One wave of episodes (one per env): the student or the teacher drives (``drivers``: True where the teacher
    does), the teacher labels every step. Returns the episodes (sensed entries, teacher actions) and their stats."""
    from .controllers import idle_action

    B = env.num_envs
    obs, info = env.reset(seed=seeds)
    mus = env.core.mu.copy()
    teacher.reset([{"mu": float(m)} for m in mus])
    student.reset([{}] * B)
    xs, ys = [], []
    done = np.zeros(B, dtype=bool)
    length = np.zeros(B, dtype=np.int64)
    success = np.zeros(B, dtype=bool)
    peak = np.zeros(B)
    idle = idle_action(env.config)
    for _ in range(env.config.max_episode_steps + 1):
        label = teacher.act(obs)
        mine = student.act(obs)
        xs.append(obs[:, columns].astype(np.float32))
        ys.append(label.astype(np.float32))
        act = np.where(drivers[:, None], label, mine)
        act = np.where(done[:, None], idle, act)
        obs, _, term, trunc, inf = env.core.step(act, advance=np.flatnonzero(~done))
        live = ~done
        length[live] += 1
        ended = live & (term | trunc)
        success[ended] = inf["is_success"][ended]
        peak[ended] = env.core.peak_pinch[ended]
        done |= ended
        if done.all():
            break
    x, y = np.stack(xs, axis=1), np.stack(ys, axis=1)  # (B, T, .)
    episodes = [(x[b, :length[b]], y[b, :length[b]]) for b in range(B)]
    by_student = ~drivers
    stats = {"episodes": int(B), "teacher_driven": int(drivers.sum()), "steps": int(length.sum()),
             "student_success": float(success[by_student].mean()) if by_student.any() else math.nan,
             "teacher_success": float(success[drivers].mean()) if drivers.any() else math.nan}
    return episodes, stats


def _fit(net, data: list[tuple[np.ndarray, np.ndarray]], config: DaggerConfig, optimiser, rng) -> float:
    """``grad_steps`` Adam steps on whole episodes from ``data``; the mean loss of the last tenth."""
    import torch

    q = torch.tensor(config.quantiles, dtype=torch.float32)
    losses = []
    net.train()
    for _ in range(config.grad_steps):
        pick = rng.choice(len(data), size=min(config.batch_episodes, len(data)), replace=False)
        T = max(len(data[k][0]) for k in pick)
        x = np.zeros((len(pick), T, data[0][0].shape[1]), dtype=np.float32)
        y = np.zeros((len(pick), T, 2), dtype=np.float32)
        m = np.zeros((len(pick), T), dtype=np.float32)
        for j, k in enumerate(pick):
            n = len(data[k][0])
            x[j, :n], y[j, :n], m[j, :n] = data[k][0], data[k][1], 1.0
        pred, _ = net(torch.from_numpy(x))
        loss = pinball(pred, torch.from_numpy(y), torch.from_numpy(m), q)
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optimiser.step()
        losses.append(loss.item())
    net.eval()
    return float(np.mean(losses[-max(1, len(losses) // 10):]))


def _set_normaliser(net, data: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """The student's input statistics from the first iteration's frames (fixed afterwards: the student's inputs mean
    the same throughout its training); entries that never vary (a sensor that is absent) are passed unscaled."""
    import torch

    frames = np.concatenate([x for x, _ in data])
    std = frames.std(axis=0)
    net.obs_mean.copy_(torch.as_tensor(frames.mean(axis=0)))
    net.obs_std.copy_(torch.as_tensor(np.where(std > 1e-6, std, 1.0)))


def train_dagger(config: DaggerConfig, out_dir: str | Path, progress: bool = True) -> dict[str, Any]:
    """Train a student by DAgger into ``out_dir`` (:data:`~.learners.dagger_layout.LAYOUT`); returns the summary."""
    import torch

    from ..envs.grasp_lift import GraspLiftVectorEnv
    from .training import BestModel

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / LAYOUT.config, json.dumps({"learner": NAME, "config": to_dict(config)}, indent=1) + "\n")
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    task = config.training_task()
    env = GraspLiftVectorEnv(config.n_envs, task)
    teacher = teacher_policy(config)
    columns = student_columns(env.core)
    net = make_student_net(len(columns), config.hidden, config.memory)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    student = StudentPolicy(net, columns, name=f"student (seed {config.seed})")
    meta = {"learner": NAME, "name": f"DAgger student (seed {config.seed})", "n_in": int(len(columns)),
            "hidden": config.hidden, "memory": config.memory, "actor_columns": columns.tolist(),
            "config": to_dict(config)}
    selector = BestModel(config, out)
    data: list[tuple[np.ndarray, np.ndarray]] = []
    history = []
    steps = 0
    t0 = time.perf_counter()
    wave = 0
    for it in range(config.iterations):
        share = config.teacher_drives * config.beta_decay ** it
        it_stats = []
        for _ in range(config.waves):
            drivers = rng.random(config.n_envs) < share
            seeds = [config.seed + wave * config.n_envs + i for i in range(config.n_envs)]
            episodes, stats = _rollouts(env, student, teacher, columns, drivers, seeds)
            data += episodes
            it_stats.append(stats)
            steps += stats["steps"]
            wave += 1
        if it == 0:
            _set_normaliser(net, data)
        loss = _fit(net, data, config, optimiser, rng)
        path = out / LAYOUT.checkpoint.format(it)
        path.parent.mkdir(exist_ok=True)
        save_student(net, path, {**meta, "iteration": it})

        def keep(path: Path = path) -> None:
            atomic_write(out / LAYOUT.model, lambda p: shutil.copyfile(path, p))
            atomic_write_text(meta_path(out / LAYOUT.model), meta_path(path).read_text())

        rec = selector.consider_policy(StudentPolicy(copy.deepcopy(net), columns, "validation"), steps, path, keep)
        driven = [s for s in it_stats if s["episodes"] > s["teacher_driven"]]
        row = {"iteration": it, "teacher_share": share, "episodes": sum(s["episodes"] for s in it_stats),
               "dataset_episodes": len(data), "agent_steps": steps, "loss": loss,
               "student_rollout_success": (float(np.nanmean([s["student_success"] for s in driven]))
                                           if driven else None),
               "validation_success_by_mu": rec["success_by_mu"], "validation_force_cost_N": rec["force_cost_N"],
               "elapsed_s": time.perf_counter() - t0}
        history.append(row)
        if progress:
            print(f"  dagger seed {config.seed} iteration {it}: {len(data)} episodes, loss {loss:.4f}, validation "
                  f"success {rec['success_by_mu']}, force cost {rec['force_cost_N']:.3f} N, "
                  f"{row['elapsed_s']:.0f} s", file=sys.stderr)
    train_s = time.perf_counter() - t0
    best = selector.best
    summary = {"learner": NAME, "seed": config.seed, "memory": config.memory, "teacher": config.teacher,
               "train_s": train_s, "agent_steps": steps, "agent_steps_per_s": steps / train_s,
               "best_iteration": history[[h["agent_steps"] for h in history].index(best["timesteps"])]["iteration"],
               "best_validation": best, "iterations": history, "model": str(out / LAYOUT.model)}
    atomic_write(out / LAYOUT.summary, lambda p: p.write_text(json.dumps(summary, indent=2)))
    return summary


def select_students(config: DaggerConfig, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
    """Validate saved students ``checkpoints`` ((iteration, path), in order) with ``config``'s validation settings and
    ship the best as ``out/student.pt`` (``msdgrasp select``); returns the summary's selection entries."""
    from .recurrent import read_student_meta
    from .training import BestModel

    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    selector = BestModel(config, out)
    for it, path in checkpoints:

        def keep(path: Path = path) -> None:
            meta = read_student_meta(path, NAME)
            atomic_write(out / LAYOUT.model, lambda p: shutil.copyfile(path, p))
            atomic_write_text(meta_path(out / LAYOUT.model), json.dumps({**meta, "config": to_dict(config)}, indent=1))

        selector.consider_policy(StudentPolicy.load(path, "validation"), it, path, keep)
    return {"best_iteration": selector.best["timesteps"], "checkpoints_validated": len(checkpoints),
            "best_validation": selector.best, "selection_s": time.perf_counter() - t0}
