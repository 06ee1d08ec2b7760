"""Saved models and the training config they were made with (no training code here).

:class:`TrainConfig` is one training run's full description (``configs/train/ppo.yaml`` spells out its
defaults); :func:`load_model` loads a saved SB3 model with the algorithm named in the config saved next to
it. Controllers and evaluation need these to run a model; training needs them to make one. Keeping them
here keeps ``agents/`` acyclic: models <- controllers <- evaluation <- training <- seeds (<- cli.rl).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

from ..envs.core import GraspLiftConfig, RandomizationConfig, RewardConfig
from ..physics.config import ConfigError, check_choice, from_dict, read_yaml

ALGOS = ("ppo", "sac")


@dataclass(frozen=True)
class TrainConfig:
    """A training run (hyper-parameters are passed to the SB3 algorithm as given).

    These defaults ARE the default run: ``configs/train/ppo.yaml`` spells the same values out (a test
    checks that both agree), so ``msdgrasp train`` with or without ``--config configs/train/ppo.yaml``
    trains the same thing.
    """

    algo: str = "ppo"
    total_timesteps: int = 900_000
    #: 32 batched envs: the physics runs 1.6x more agent steps/s per core than at 16 (SIMD across tissues)
    n_envs: int = 32
    seed: int = 0
    checkpoint_every: int = 25_000
    torch_threads: int = 1
    policy_net: tuple[int, ...] = (64, 64)
    #: PPO only: initial log standard deviation of the action noise. With gSDE (ppo.use_sde, the default)
    #: the noise is exp(log_std) times the policy's latent features (-2 is the SB3 zoo's gSDE setting; -1
    #: measured: with -2 seed 0 never learned low friction, with -1 it held 100% at every validation mu).
    #: Without gSDE, SB3's default 0 is a standard deviation of 1 in action units.
    log_std_init: float = -1.0
    #: PPO with gSDE: squash the policy's actions with tanh (SB3 ``squash_output``) instead of clipping them
    #: to [-1, 1]. A clipped Gaussian whose mean has drifted past a bound always acts at the bound, so its
    #: return no longer depends on the mean there and nothing pulls it back (a set-point "stuck" at 5 N while
    #: the jaws close); through tanh the mean keeps a gradient. SAC squashes always (this field is ignored).
    squash_actions: bool = True
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
    lr_schedule: str = "linear"
    #: PPO only: the critic also sees the privileged entries of the observation (mu, stiffness and mass
    #: scales, node displacements); the actor does not (agents/networks.py). Needs env.privileged_obs.
    asymmetric_critic: bool = True
    ppo: dict = field(default_factory=lambda: {
        "learning_rate": 1e-3, "n_steps": 128, "batch_size": 1024, "n_epochs": 10, "gamma": 0.999,
        "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
        "use_sde": True, "sde_sample_freq": 4,
    })
    sac: dict = field(default_factory=lambda: {
        "learning_rate": 3e-4, "buffer_size": 200_000, "batch_size": 256, "gamma": 0.99, "tau": 0.005,
        "learning_starts": 2000, "train_freq": 1, "gradient_steps": 1,
    })
    #: the training task: the default GraspLift task, with the privileged entries the critic needs,
    #: friction drawn log-uniformly (the low-friction end, where grasps fail, comes up twice as often), a
    #: pinch action that spends more of its range on light grips (action 0: 1.25 N) and a pull-speed action
    #: (action 0: 10 mm/s) instead of a travel set-point (docs/task-design.md, session 3), and a peak-pinch
    #: charge scaled by mu / 0.4, which follows the ratio to the minimal slip-free force (session 6)
    env: GraspLiftConfig = field(default_factory=lambda: GraspLiftConfig(
        privileged_obs=True, pinch_action_exponent=2.0, pull_action="forward_speed",
        reward=RewardConfig(peak_force_mu_ref=0.4),
        randomization=RandomizationConfig(mu_distribution="log_uniform")))

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
        if isinstance(self.log_std_init, bool) or not isinstance(self.log_std_init, (int, float)) or not -5.0 <= self.log_std_init <= 1.0:
            raise ConfigError(f"log_std_init must be a number in [-5, 1], got {self.log_std_init!r}")
        if not isinstance(self.squash_actions, bool):
            raise ConfigError(f"squash_actions must be true or false, got {self.squash_actions!r}")
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
        if self.squash_actions and self.algo == "ppo" and not self.ppo.get("use_sde", False):
            raise ConfigError("squash_actions: true needs ppo.use_sde: true (SB3 squashes gSDE actions only); "
                              "set squash_actions: false to train PPO without gSDE")

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
