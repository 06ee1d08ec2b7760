"""The recurrent learner (``msdgrasp train --learner recurrent``): a student with memory learns, by DAgger, to act as a
privileged teacher acts, from what the grasper senses; then PPO fine-tunes it (:mod:`.recurrent_ppo`).

The teacher is told what no grasper senses: the episode's friction (``slipfeedback:...,told=1``: the estimating
controller with its estimate replaced by the true mu; it closes to the same probe grip, or less where the friction
needs less, so the closing the student sees is the one the friction shows in). The student (:mod:`.recurrent`) reads
only the actor's sensed entries and must infer from its history what the teacher is told. DAgger (Ross, Gordon and
Bagnell 2011): in iteration 0 the teacher drives (``teacher_drives`` of the episodes; then x ``beta_decay`` per
iteration), then the student; in every step of every episode the teacher, run in the student's shadow on the same
observations, labels what it would do, so the data covers the states the student's own mistakes lead to. After each
iteration the student is fitted on all episodes so far (whole episodes, from a zero memory, as it runs), its
checkpoint validated on the training task's validation episodes and the best kept.

The loss is the pinball (quantile) loss per action: at ``quantiles[0]`` > 0.5 the student's grip is an upper quantile
of the teacher's grips over the frictions its history cannot tell apart (a grip too light loses the grasp; one too
heavy costs force), where a squared loss would grip at their mean. Selection (``selection: grasps``): the checkpoint
with the highest lowest Wilson bound of validation success over mu, then the least force: no checkpoint trades a
low-friction grasp for force. Every checkpoint of both stages is a candidate (``checkpoints/student_<k>.pt``, DAgger's
iterations first). Reasons and measurements: docs/design.md, "Learned control with memory".
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
from .learners.recurrent_layout import LAYOUT, NAME
from .models import default_training
from .protocol import VALIDATION_SEED_OFFSET, check_not_sealed
from .recurrent import MEMORIES, StudentPolicy, make_student_net, meta_path, pad_episodes, pinball, save_student
from .recurrent_ppo import run_wave

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
class RecurrentConfig:
    """One recurrent run, DAgger then PPO (``configs/train/recurrent.yaml``); reasons for the values: docs/design.md."""

    #: the run's seed: the rollout envs (env i reset with seed + i), the drivers' draws and the networks
    seed: Annotated[Int, Ge(0)] = 0
    #: the privileged teacher, a controller spec told the episode's mu by its reset info
    teacher: str = TEACHER
    #: what the student remembers: "gru" (a recurrent state over the episode) or "none" (the current frame only)
    memory: Literal["gru", "none"] = "gru"
    #: width of the student's layers (input, GRU, head)
    hidden: Annotated[Int, Ge(4)] = 64
    #: DAgger iterations: each runs episodes_per_iteration episodes, then fits the student on all so far
    iterations: Annotated[Int, Ge(0)] = 6
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
    #: PPO waves after DAgger (each: n_envs episodes with the actor's Gaussian actions, then ppo_epochs passes over
    #: them; agents/recurrent_ppo.py); 0: no PPO stage. With iterations 0: recurrent PPO from scratch
    ppo_waves: Annotated[Int, Ge(0)] = 0
    #: PPO waves between validations (each validated actor a candidate for the shipped model; the last wave's too)
    ppo_validate_every: Annotated[Int, Ge(1)] = 5
    ppo_learning_rate: Positive = 3e-4
    ppo_epochs: Annotated[Int, Ge(1)] = 4
    #: whole episodes per PPO minibatch
    ppo_minibatch_episodes: Annotated[Int, Ge(1)] = 16
    ppo_clip: Positive = 0.2
    #: undiscounted by default, as the default training (a later lift is worth an early one)
    ppo_gamma: Unit = 1.0
    ppo_lam: Unit = 0.95
    ppo_value_coef: Annotated[Real, Ge(0)] = 0.5
    ppo_max_grad_norm: Positive = 1.0
    #: log of the action noise's initial std (per action; learned)
    ppo_log_std_init: Annotated[Real, Ge(-5), Le(1)] = -1.5
    #: width of the privileged critic's two layers
    ppo_critic_hidden: Annotated[Int, Ge(4)] = 128
    #: weight of the pinball loss to the shadow teacher's labels at the first and at the last PPO wave (linear
    #: between): the anchor that keeps what DAgger taught; [0, 0]: PPO alone (the teacher is never read)
    bc_coef: tuple[Annotated[Real, Ge(0)], Annotated[Real, Ge(0)]] = (5.0, 0.5)
    #: validation episodes per mu of every iteration's student (on the training task, seed + VALIDATION_SEED_OFFSET + i)
    validation_episodes: Annotated[Int, Ge(1)] = 24
    validation_mu: tuple[Annotated[Real, Ge(0)], ...] = (0.2, 0.3, 0.5, 0.8)
    #: how a checkpoint is picked: "grasps" (the lowest Wilson bound of success over mu, then force) or "success"
    #: (the mean success, then force: the SB3 training's rule)
    selection: Literal["grasps", "success"] = "grasps"
    #: torch threads of the run (the networks are small: more threads contend with the physics and with parallel seeds)
    torch_threads: Annotated[Int, Ge(1)] = 1
    #: the task the student acts on (the default training's: the benchmark task with a privileged block for teachers)
    env: GraspLiftConfig = field(default_factory=_default_env)
    #: the perturbations the episodes are drawn from (the default training's ranges)
    train_randomization: RandomizationConfig = field(default_factory=_default_randomization)

    @property
    def reads_teacher(self) -> bool:
        """Whether the teacher's labels train the actor (DAgger, or PPO's anchor): False for PPO from scratch."""
        return bool(self.iterations or (self.ppo_waves and max(self.bc_coef) > 0))

    @property
    def waves(self) -> int:
        """Waves of n_envs episodes per iteration."""
        return self.episodes_per_iteration // self.n_envs

    def seed_sets(self) -> list[tuple[int, int, str]]:
        """Every run of reset seeds the training derives from ``seed`` (first, count, how)."""
        n = (self.iterations * self.waves + self.ppo_waves) * self.n_envs
        return [(self.seed, n, f"rollout episodes: seed + i, i < (iterations x episodes_per_iteration / n_envs + "
                               f"ppo_waves) x n_envs = {n}"),
                (self.seed + VALIDATION_SEED_OFFSET, self.validation_episodes,
                 f"validation episodes: seed + {VALIDATION_SEED_OFFSET} + i, i < validation_episodes = "
                 f"{self.validation_episodes}")]

    def __post_init__(self) -> None:
        if self.episodes_per_iteration % self.n_envs:
            raise ConfigError(f"episodes_per_iteration must be a multiple of n_envs = {self.n_envs}, got "
                              f"{self.episodes_per_iteration}")
        if self.iterations == 0 and self.ppo_waves == 0:
            raise ConfigError("iterations and ppo_waves are both 0: nothing would train; allowed: either >= 1")
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
    def load(cls, path: str | Path) -> "RecurrentConfig":
        return from_dict(cls, read_extending_yaml(path), where=Path(path).name)


def teacher_policy(config: RecurrentConfig):
    """The teacher of ``config`` (ConfigError naming the field where its spec is not a controller told mu)."""
    from .controllers import is_controller, make_policy

    try:
        teacher = make_policy(config.teacher, config.env) if is_controller(config.teacher) else None
    except (ValueError, ConfigError) as exc:
        raise ConfigError(f"teacher: {exc}") from None
    if not getattr(teacher, "told_mu", False):
        raise ConfigError(f"teacher must be a slip-feedback controller told mu ('slipfeedback:...,told=1,...'), got "
                          f"{config.teacher!r}")
    return teacher


def student_columns(core) -> np.ndarray:
    """The observation entries of the task ``core`` the student sees: the sensed entries of every frame, never the
    privileged ones."""
    return np.flatnonzero(actor_mask(len(OBS_NAMES), core.frame_dim, core.config.obs_history))


def _dagger_wave(env, student: StudentPolicy, teacher, columns: np.ndarray, drivers: np.ndarray,
                 seeds: list[int]) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, float]]:
    """One DAgger wave: the student or the teacher drives (``drivers``: True where the teacher does), the teacher
    labels. Returns the episodes (sensed entries, teacher actions) and their stats."""
    student.reset([{}] * env.num_envs)

    def act(obs: np.ndarray, label: np.ndarray) -> np.ndarray:
        return np.where(drivers[:, None], label, student.act(obs))

    wave = run_wave(env, act, teacher, seeds)
    episodes = [(o[:, columns], y) for o, y in zip(wave.obs, wave.labels)]
    by_student = ~drivers
    stats = {"episodes": int(env.num_envs), "teacher_driven": int(drivers.sum()), "steps": wave.steps,
             "student_success": float(wave.success[by_student].mean()) if by_student.any() else math.nan,
             "teacher_success": float(wave.success[drivers].mean()) if drivers.any() else math.nan}
    return episodes, stats


def _fit(net, data: list[tuple[np.ndarray, np.ndarray]], config: RecurrentConfig, optimiser, rng) -> float:
    """``grad_steps`` Adam steps on whole episodes from ``data``; the mean loss of the last tenth."""
    import torch

    q = torch.tensor(config.quantiles, dtype=torch.float32)
    losses = []
    net.train()
    for _ in range(config.grad_steps):
        pick = rng.choice(len(data), size=min(config.batch_episodes, len(data)), replace=False)
        T = max(len(data[k][0]) for k in pick)
        x, y = (pad_episodes([data[k][i] for k in pick], T) for i in (0, 1))
        m = pad_episodes([np.ones(len(data[k][0])) for k in pick], T)
        pred, _ = net(torch.from_numpy(x))
        loss = pinball(pred, torch.from_numpy(y), torch.from_numpy(m), q)
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        optimiser.step()
        losses.append(loss.item())
    net.eval()
    return float(np.mean(losses[-max(1, len(losses) // 10):]))


def train_recurrent(config: RecurrentConfig, out_dir: str | Path, progress: bool = True) -> dict[str, Any]:
    """Train a recurrent actor into ``out_dir`` (:data:`~.learners.recurrent_layout.LAYOUT`): DAgger's iterations,
    then PPO's waves, every checkpoint validated and the best shipped; returns the summary (``summary.json``)."""
    import torch

    from ..envs.grasp_lift import GraspLiftVectorEnv
    from .recurrent_ppo import RecurrentPPO, set_statistics
    from .training import BestModel

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / LAYOUT.config, json.dumps({"learner": NAME, "config": to_dict(config)}, indent=1) + "\n")
    torch.set_num_threads(config.torch_threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    env = GraspLiftVectorEnv(config.n_envs, config.training_task())
    teacher = teacher_policy(config)
    columns = student_columns(env.core)
    net = make_student_net(len(columns), config.hidden, config.memory)
    student = StudentPolicy(net, columns, name=f"student (seed {config.seed})")
    stages = ([f"DAgger from {config.teacher}"] if config.iterations else []) + (
        [f"PPO (anchor {config.bc_coef[0]:g} -> {config.bc_coef[1]:g})"] if config.ppo_waves else [])
    meta = {"learner": NAME, "name": f"recurrent {config.memory} (seed {config.seed})", "n_in": int(len(columns)),
            "hidden": config.hidden, "memory": config.memory, "actor_columns": columns.tolist(),
            "stages": stages, "config": to_dict(config)}
    selector = BestModel(config, out)
    history: list[dict[str, Any]] = []
    progress_log = _Progress(config, progress)
    t0 = time.perf_counter()
    steps = wave = checkpoint = 0

    def validate(row: dict[str, Any]) -> None:
        nonlocal checkpoint
        path = out / LAYOUT.checkpoint.format(checkpoint)
        path.parent.mkdir(exist_ok=True)
        save_student(net, path, {**meta, "checkpoint": checkpoint})

        def keep() -> None:
            atomic_write(out / LAYOUT.model, lambda p: shutil.copyfile(path, p))
            atomic_write_text(meta_path(out / LAYOUT.model), meta_path(path).read_text())

        rec = selector.consider_policy(StudentPolicy(copy.deepcopy(net), columns, "validation"), steps, path, keep)
        row.update(checkpoint=checkpoint, agent_steps=steps, validation_success_by_mu=rec["success_by_mu"],
                   validation_force_cost_N=rec["force_cost_N"], elapsed_s=time.perf_counter() - t0)
        history.append(row)
        progress_log(row)
        checkpoint += 1

    def seeds() -> list[int]:
        nonlocal wave
        wave += 1
        return [config.seed + (wave - 1) * config.n_envs + i for i in range(config.n_envs)]

    # ---- DAgger -----------------------------------------------------------------------------------------------------
    data: list[tuple[np.ndarray, np.ndarray]] = []
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    for it in range(config.iterations):
        share = config.teacher_drives * config.beta_decay ** it
        it_stats = []
        for _ in range(config.waves):
            drivers = rng.random(config.n_envs) < share
            episodes, stats = _dagger_wave(env, student, teacher, columns, drivers, seeds())
            data += episodes
            it_stats.append(stats)
            steps += stats["steps"]
        if it == 0:
            set_statistics(net, np.concatenate([x for x, _ in data]))
        loss = _fit(net, data, config, optimiser, rng)
        driven = [st["student_success"] for st in it_stats if st["episodes"] > st["teacher_driven"]]
        validate({"stage": "dagger", "iteration": it, "teacher_share": share, "dataset_episodes": len(data),
                  "loss": loss, "student_rollout_success": float(np.mean(driven)) if driven else None})
    del data

    # ---- PPO --------------------------------------------------------------------------------------------------------
    if config.ppo_waves:
        ppo = RecurrentPPO(net, columns, env.core.obs_dim, config)
        for k in range(config.ppo_waves):
            ppo.reset(config.n_envs)
            wave_data = run_wave(env, lambda obs, label: ppo.sample(obs, rng), teacher, seeds())
            if k == 0 and config.iterations == 0:  # (from scratch: the actor's input statistics from its first wave)
                set_statistics(net, np.concatenate([o[:, columns] for o in wave_data.obs]))
            steps += wave_data.steps
            frac = k / max(config.ppo_waves - 1, 1)
            bc = (1 - frac) * config.bc_coef[0] + frac * config.bc_coef[1]
            stats = ppo.update(wave_data, bc, rng)
            if (k + 1) % config.ppo_validate_every == 0 or k + 1 == config.ppo_waves:
                validate({"stage": "ppo", "wave": k, "bc_coef": bc, "rollout_success": float(wave_data.success.mean()),
                          **stats})
    train_s = time.perf_counter() - t0
    best = selector.best
    summary = {"learner": NAME, "seed": config.seed, "memory": config.memory, "stages": stages,
               "reads_teacher": config.reads_teacher,
               "train_s": train_s, "agent_steps": steps, "agent_steps_per_s": steps / train_s,
               "best_checkpoint": next(h["checkpoint"] for h in history if h["agent_steps"] == best["timesteps"]),
               "best_validation": best, "history": history, "model": str(out / LAYOUT.model)}
    atomic_write(out / LAYOUT.summary, lambda p: p.write_text(json.dumps(summary, indent=2)))
    return summary


class _Progress:
    """One line per validated checkpoint on stderr (``progress``)."""

    def __init__(self, config: RecurrentConfig, on: bool) -> None:
        self.seed, self.on = config.seed, on

    def __call__(self, row: dict[str, Any]) -> None:
        if not self.on:
            return
        where = f"iteration {row['iteration']}" if row["stage"] == "dagger" else f"PPO wave {row['wave']}"
        success = ", ".join(f"{m}: {v:.2f}" for m, v in row["validation_success_by_mu"].items())
        print(f"  recurrent seed {self.seed} {where}: validation success {success}; force cost "
              f"{row['validation_force_cost_N']:.3f} N; {row['elapsed_s']:.0f} s", file=sys.stderr)


def select_students(config: RecurrentConfig, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
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
