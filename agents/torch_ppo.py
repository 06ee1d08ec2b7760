"""Torch-native PPO (rsl-rl-lib, the learner of Isaac Lab) on a batched GraspLift core: the GPU path.

Stable-Baselines3 steps a VecEnv of NumPy arrays and moves every batch through the host; at thousands of
GPU envs per step that per-step overhead is what a torch-native learner avoids. Here rsl-rl's
``OnPolicyRunner`` drives :class:`GraspLiftTorchEnv`, which wraps either core:

* :class:`~msdgrasp.envs.cuda_core.CudaGraspLiftCore` (``backend: cuda``): actions go to the GPU task as
  CUDA tensors and observations, rewards and flags come back as zero-copy views of its device arrays
  (numba's ``__cuda_array_interface__``); nothing crosses to the host but the episode statistics of the
  log (one small copy per step where an episode ended);
* :class:`~msdgrasp.envs.core.GraspLiftCore` (``backend: cpu``): the same learner on the CPU core (NumPy in,
  torch out), so the learner is testable and comparable without a GPU.

The actor sees the task observation; the critic also sees the privileged entries (mu, scales, node
displacements), as in the SB3 training's asymmetric critic. The trained actor is exported as TorchScript
(``policy.pt``), which :class:`TorchScriptPolicy` runs in ``msdgrasp evaluate``.

Needs the ``gpu`` extra (``pip install 'msdgrasp[gpu]'``: numba-cuda and rsl-rl-lib).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any, Literal, Sequence

import numpy as np
from annotated_types import Ge, Le

from ..envs.core import OBS_NAMES, GraspLiftConfig, GraspLiftCore, actor_mask
from ..physics.device_layout import Precision
from ..physics.config import (
    Bool, ConfigError, Int, NonNegative, Positive, Real, atomic_write, atomic_write_text, config_dataclass, from_dict,
    read_extending_yaml, to_dict,
)
from .controllers import TorchScriptPolicy
from .learners.rsl_layout import LAYOUT, NAME, RUNNER_CHECKPOINT, meta_path
from .models import TrainConfig
from .protocol import VALIDATION_SEED_OFFSET, check_not_sealed

Unit = Annotated[Real, Ge(0), Le(1)]


@config_dataclass
class TorchPPOConfig:
    """One torch-native PPO run (``configs/train/rsl_ppo.yaml`` spells out the defaults)."""

    #: where the task runs: "cuda" (CudaGraspLiftCore: the whole step on the GPU) or "cpu" (GraspLiftCore)
    backend: Literal["cpu", "cuda"] = "cuda"
    #: the training task's tissue arrays, on either backend: float64 or float32 (half the memory traffic: 1.2-1.3x per
    #: tissue in a CPU batch; its error: ``msdgrasp bench precision`` / ``physics``). Validation runs float64
    precision: Precision = "float64"
    num_envs: Annotated[Int, Ge(1)] = 4096
    seed: Annotated[Int, Ge(0)] = 0
    #: PPO iterations (each: steps_per_env x num_envs agent steps, then the update)
    iterations: Annotated[Int, Ge(1)] = 150
    steps_per_env: Annotated[Int, Ge(1)] = 32
    hidden_dims: tuple[Annotated[Int, Ge(1)], ...] = (64, 64)
    activation: Literal["elu", "relu", "tanh"] = "elu"
    #: running mean / std normalisation of the observations (inside the exported policy)
    obs_normalization: Bool = True
    #: initial std of the action noise (of the Gaussian before the squash, with squash_actions)
    init_std: Positive = 0.5
    #: tanh-squashed Gaussian actions (agents/rsl_distributions.py) instead of clipping them to [-1, 1]
    squash_actions: Bool = False
    learning_rate: Positive = 1e-3
    #: "adaptive": the learning rate follows the KL to desired_kl (rsl-rl); "fixed"; "linear": from
    #: learning_rate down to 0 at the last iteration (SB3's recipe, which settles the policy at the end)
    schedule: Literal["adaptive", "fixed", "linear"] = "adaptive"
    desired_kl: Positive = 0.01
    epochs: Annotated[Int, Ge(1)] = 5
    mini_batches: Annotated[Int, Ge(1)] = 4
    gamma: Unit = 0.999
    lam: Unit = 0.95
    clip: Positive = 0.2
    entropy_coef: NonNegative = 0.0
    value_loss_coef: NonNegative = 1.0
    max_grad_norm: Positive = 1.0
    #: the critic also sees the privileged observation (env.privileged_obs must be on); the actor does not
    asymmetric_critic: Bool = True
    #: PPO iterations between checkpoints; after training every checkpoint (and the last iteration's policy)
    #: runs the validation episodes and the best is shipped as policy.pt, as the SB3 training keeps its best
    #: checkpoint (PPO is not monotonic); 0: only the last policy
    checkpoint_every: Annotated[Int, Ge(0)] = 15
    #: validation on the CPU env, episodes per mu, of every checkpoint (0: none; then policy.pt is the last)
    validation_episodes: Annotated[Int, Ge(0)] = 6
    validation_mu: tuple[Annotated[Real, Ge(0)], ...] = (0.2, 0.3, 0.5, 0.7, 0.9)
    #: the task: the SB3 training's (TrainConfig.env), so both learners train and are judged on the same task
    env: GraspLiftConfig = field(default_factory=lambda: TrainConfig().env)

    def seed_sets(self) -> list[tuple[int, int, str]]:
        """Every run of reset seeds the training derives from ``seed``: (first, count, how): the training envs (the CPU
        env i reset with seed + i; the GPU's generators and the networks' initialisation seeded with seed) and the
        validation episodes."""
        sets = [(self.seed, self.num_envs, f"training envs: seed + i, i < num_envs = {self.num_envs}")]
        if self.validation_episodes:
            sets.append((self.seed + VALIDATION_SEED_OFFSET, self.validation_episodes,
                         f"validation episodes: seed + {VALIDATION_SEED_OFFSET} + i, i < validation_episodes = "
                         f"{self.validation_episodes}"))
        return sets

    def __post_init__(self) -> None:
        for first, count, via in self.seed_sets():  # (a training never draws the sealed evaluation episodes)
            check_not_sealed(first, count, "seed", value=self.seed, via=via)
        if self.asymmetric_critic and not self.env.privileged_obs:
            raise ConfigError("asymmetric_critic needs env.privileged_obs: true (the critic's extra entries)")

    def training_task(self, progress: float = 1.0) -> GraspLiftConfig:
        """The task the training draws its episodes from: ``env`` (this learner has no randomisation of its own)."""
        return self.env

    @property
    def steps_per_iteration(self) -> int:
        """Agent steps collected per PPO iteration (all envs)."""
        return self.steps_per_env * self.num_envs

    @property
    def total_steps(self) -> int:
        """Agent steps of the whole run (what SB3 calls total_timesteps)."""
        return self.iterations * self.steps_per_iteration

    @classmethod
    def load(cls, path: str | Path) -> "TorchPPOConfig":
        """The config at ``path``, strictly; ``extends:`` builds it on another file (see :meth:`TrainConfig.load`)."""
        return from_dict(cls, read_extending_yaml(path), where=Path(path).name)

    def runner_cfg(self) -> dict[str, Any]:
        """rsl-rl's runner configuration of this run."""
        groups = {"actor": ["policy"], "critic": ["critic"] if self.asymmetric_critic else ["policy"]}
        distribution = (f"{__package__}.rsl_distributions:SquashedGaussianDistribution" if self.squash_actions
                        else "GaussianDistribution")
        mlp = {"class_name": "MLPModel", "hidden_dims": list(self.hidden_dims), "activation": self.activation,
               "obs_normalization": self.obs_normalization}
        # rsl-rl saves a checkpoint every save_interval iterations and after the last one
        selecting = self.checkpoint_every and self.validation_episodes
        return {
            "num_steps_per_env": self.steps_per_env, "obs_groups": groups,
            "save_interval": self.checkpoint_every if selecting else self.iterations,
            "check_for_nan": True, "multi_gpu": None, "logger": "tensorboard",
            "actor": {**mlp, "distribution_cfg": {"class_name": distribution, "init_std": self.init_std,
                                                  "std_type": "log"}},
            "critic": mlp,
            "algorithm": {
                "class_name": "PPO", "num_learning_epochs": self.epochs, "num_mini_batches": self.mini_batches,
                "clip_param": self.clip, "gamma": self.gamma, "lam": self.lam, "value_loss_coef": self.value_loss_coef,
                "entropy_coef": self.entropy_coef, "learning_rate": self.learning_rate,
                "max_grad_norm": self.max_grad_norm, "desired_kl": self.desired_kl,
                # (rsl-rl knows adaptive and fixed; linear is a fixed rate that train_torch lowers per update)
                "schedule": "fixed" if self.schedule == "linear" else self.schedule,
            },
        }


def rsl_vec_env() -> type:
    """rsl-rl's ``VecEnv`` base class; ImportError naming the extra to install where rsl-rl is missing (so a learner
    can check for it before a run)."""
    try:
        import rsl_rl  # noqa: F401
        from rsl_rl.env import VecEnv
    except ImportError as exc:
        raise ImportError(f"{exc}; the torch-native PPO needs rsl-rl-lib: pip install 'msdgrasp[gpu]'") from None
    return VecEnv


def actor_columns(config: GraspLiftConfig, frame_dim: int) -> np.ndarray:
    """Indices of the observation entries the actor sees (the task entries of every frame)."""
    return np.flatnonzero(actor_mask(len(OBS_NAMES), frame_dim, config.obs_history))


def make_torch_env(core, device: str, seed: int = 0):
    """The rsl-rl VecEnv of a core (:class:`GraspLiftTorchEnv`), every env reset (CPU env i seeded seed + i)."""
    VecEnv = rsl_vec_env()
    import torch
    from tensordict import TensorDict

    class GraspLiftTorchEnv(VecEnv):
        """rsl-rl's vectorised-env interface over a GraspLift core (see the module docstring).

        ``step(actions)`` returns observations ({"policy": actor entries, "critic": all}), rewards, dones
        and extras with ``time_outs`` (truncations, which PPO bootstraps) and ``log`` (success rate, peak
        pinch and slip of the episodes that ended)."""

        def __init__(self) -> None:
            self.core = core
            self.num_envs = core.num_envs
            self.num_actions = 2
            self.max_episode_length = core.config.max_episode_steps
            self.device = device
            self.cfg = to_dict(core.config)
            self.gpu = hasattr(core, "physics")
            self.columns = torch.as_tensor(actor_columns(core.config, core.frame_dim), device=device)
            if self.gpu:
                core.reset()
            else:
                for i in range(self.num_envs):
                    core.seed(i, seed + i)
                    core.reset(i)
            self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=device)

        def _tensor(self, array) -> torch.Tensor:
            if self.gpu:
                from ..envs.cuda_core import as_torch

                return as_torch(array).to(self.device)
            return torch.as_tensor(np.asarray(array), device=self.device)

        def _observations(self, obs) -> TensorDict:
            full = self._tensor(obs).float()
            return TensorDict({"policy": full[:, self.columns], "critic": full}, batch_size=[self.num_envs],
                              device=self.device)

        def get_observations(self) -> TensorDict:
            return self._observations(self.core.state.obs if self.gpu else self.core.obs)

        def step(self, actions: torch.Tensor):
            if self.gpu:
                obs, reward, terminated, truncated = self.core.step(actions.detach().to(torch.float32).contiguous())
                term, trunc = self._tensor(terminated), self._tensor(truncated)
                done = term | trunc
                ended = {}
                if bool(done.any()):
                    st = self.core.state
                    ended = {"success": self._tensor(st.is_success)[done].float(),
                             "peak_pinch_N": self._tensor(st.episode_peak_pinch)[done].float(),
                             "slip_mm": 1e3 * self._tensor(st.episode_slip)[done].float()}
            else:
                obs, reward, term_np, trunc_np, info = self.core.step(actions.detach().cpu().numpy())
                done_np = term_np | trunc_np
                ended = {}
                if done_np.any():
                    ended = {"success": torch.as_tensor(info["is_success"][done_np], dtype=torch.float32),
                             "peak_pinch_N": torch.as_tensor(info["peak_pinch_N"][done_np], dtype=torch.float32),
                             "slip_mm": torch.as_tensor(1e3 * info["slip_distance_m"][done_np], dtype=torch.float32)}
                    for i in np.flatnonzero(done_np):
                        self.core.reset(int(i))
                    obs = self.core.obs
                term, trunc = (torch.as_tensor(term_np, device=self.device),
                               torch.as_tensor(trunc_np, device=self.device))
                done = term | trunc
            self.episode_length_buf += 1
            self.episode_length_buf[done] = 0
            extras = {"time_outs": trunc, "log": {f"/episode/{k}": v.mean() for k, v in ended.items()}}
            return self._observations(obs), self._tensor(reward).float(), done.long(), extras

    return GraspLiftTorchEnv()


def train_torch(config: TorchPPOConfig, out_dir: str | Path, progress: bool = True) -> dict[str, Any]:
    """Train with rsl-rl's PPO; write ``policy.pt`` (+ ``policy.json``), ``summary.json`` and tensorboard logs
    (``progress=False``: no per-iteration log, printed or tensorboard).

    With ``validation_episodes`` > 0, every checkpoint (``checkpoint_every`` iterations, and the last) is
    exported to ``checkpoints/policy_<iteration>.pt`` and runs the validation episodes on the CPU env, seeded
    apart from ``msdgrasp evaluate``'s; the best (success, then force: :class:`~.training.BestModel`, as the
    SB3 training selects) is ``policy.pt``, the history ``validation.json``. Else ``policy.pt`` is the last.

    Returns the summary: training time (``train_s``, rollouts and updates; ``selection_s`` after it), agent
    steps, and the shipped policy's iteration and validation success and peak pinch per mu."""
    rsl_vec_env()
    import torch
    from rsl_rl.runners import OnPolicyRunner

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    np.random.seed(config.seed)
    if config.backend == "cuda":
        from ..envs.cuda_core import CudaGraspLiftCore

        core = CudaGraspLiftCore(config.env, config.num_envs, seed=config.seed, precision=config.precision)
        device = "cuda" if torch.cuda.is_available() else "cpu"  # (the simulator: torch on the CPU)
    else:
        core = GraspLiftCore(config.env, config.num_envs, config.precision)
        device = "cpu"
    env = make_torch_env(core, device, config.seed)
    runner = OnPolicyRunner(env, config.runner_cfg(), log_dir=str(out / "tb"), device=device)
    if not progress:
        runner.logger.log = lambda **kwargs: None  # type: ignore[method-assign]
    if config.schedule == "linear":
        anneal_learning_rate(runner.alg, config.learning_rate, config.iterations)
    t0 = time.perf_counter()
    runner.learn(config.iterations)
    train_s = time.perf_counter() - t0
    meta = {"learner": NAME, "name": f"PPO-torch (seed {config.seed})", "actor_columns": env.columns.tolist(),
            "config": to_dict(config)}

    def export(path: Path, iteration: int) -> None:
        """The runner's actor as TorchScript at ``path``, its observation layout and iteration beside it."""
        atomic_write(path, lambda p: runner.export_policy_to_jit(str(p.parent), p.name))
        atomic_write_text(meta_path(path), json.dumps({**meta, "iteration": iteration}, indent=2))

    summary: dict[str, Any] = {"backend": config.backend, "precision": core.precision,
                               "device": device, "num_envs": config.num_envs, "seed": config.seed,
                               "iterations": config.iterations, "agent_steps": config.total_steps, "train_s": train_s,
                               "agent_steps_per_s": config.total_steps / train_s, "validation": []}
    if config.validation_episodes == 0:
        export(out / LAYOUT.model, config.iterations - 1)
    else:
        # the checkpoints rsl-rl saved (after iterations 0, k, 2k, ... and the last), exported, then validated
        every = config.checkpoint_every
        iterations = sorted({*(range(0, config.iterations, every) if every else ()), config.iterations - 1})
        checkpoints = []
        for it in iterations:
            runner.load(str(out / RUNNER_CHECKPOINT.format(it)))
            path = out / LAYOUT.checkpoint.format(it)
            path.parent.mkdir(exist_ok=True)
            export(path, it)
            checkpoints.append((it, path))
        summary.update(select_torch_checkpoints(config, checkpoints, out))
    for v in summary.values():  # (a summary is JSON: no NaN)
        if isinstance(v, float) and not math.isfinite(v):
            raise RuntimeError(f"non-finite number in the training summary: {summary}")
    atomic_write(out / LAYOUT.summary, lambda p: p.write_text(json.dumps(summary, indent=2)))
    return summary


def anneal_learning_rate(alg: Any, initial: float, updates: int) -> None:
    """Make rsl-rl's PPO ``alg`` (schedule "fixed") lower its learning rate linearly: update k (0-based) of
    ``updates`` runs at ``initial * (1 - k / updates)``, so the last one is at ``initial / updates``."""
    update = alg.update
    done = 0

    def annealed_update(*args: Any, **kwargs: Any) -> Any:
        nonlocal done
        alg.learning_rate = initial * (1.0 - min(done, updates) / updates)
        for group in alg.optimizer.param_groups:
            group["lr"] = alg.learning_rate
        done += 1
        return update(*args, **kwargs)

    alg.update = annealed_update


def select_torch_checkpoints(config: TorchPPOConfig, checkpoints: Sequence[tuple[int, Path]],
                             out: Path) -> dict[str, Any]:
    """Validate the exported ``checkpoints`` ((iteration, policy_<iteration>.pt), in order) with ``config``'s
    validation settings and ship the best (:class:`~.training.BestModel`'s key: success, then the reward's
    force charge) as ``out/policy.pt`` (+ ``policy.json``, whose config is ``config``); the history is
    ``out/validation.json``. Used by :func:`train_torch` and by ``msdgrasp select`` (:mod:`.selection`).

    Returns the summary's selection entries: the shipped iteration, its validation success and peak pinch
    per mu, the number of checkpoints validated and the time it took (``selection_s``)."""
    from .training import BestModel

    if config.validation_episodes < 1:
        raise ConfigError(f"validation_episodes must be >= 1 to select a checkpoint, got {config.validation_episodes}")
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    selector = BestModel(config, out)
    for it, path in checkpoints:

        def keep(path: Path = path) -> None:
            atomic_write(out / LAYOUT.model, lambda p: shutil.copyfile(path, p))
            meta = json.loads(meta_path(path).read_text())
            atomic_write_text(out / LAYOUT.config, json.dumps({**meta, "config": to_dict(config)}, indent=2))

        selector.consider_policy(TorchScriptPolicy(path), (it + 1) * config.steps_per_iteration, path, keep)
    best = selector.best
    return {"best_iteration": best["timesteps"] // config.steps_per_iteration - 1,
            "checkpoints_validated": len(checkpoints),
            "validation": [{"mu": float(m), "success_rate": best["success_by_mu"][m],
                            "mean_peak_pinch_N": best["peak_pinch_by_mu"][m]} for m in best["success_by_mu"]],
            "validation_success": best["success_rate"],
            "selection_s": time.perf_counter() - t0}
