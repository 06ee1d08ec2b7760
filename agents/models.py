"""The SB3 learners' training config (no training code here), and the task a saved model was trained on.

:class:`TrainConfig` is one SB3 training run's full description (``configs/train/ppo_scratch.yaml`` spells out
its defaults; ``configs/train/ppo.yaml``, the default run, extends it). Loading a model is its learner's
(:mod:`.learners`): the learner recorded beside the model says how, never a guess.
"""

from __future__ import annotations

from dataclasses import field
from pathlib import Path
from typing import Annotated, Literal

from annotated_types import Ge, Gt, Le, MinLen
from pydantic import with_config
from typing_extensions import TypedDict

from ..envs.core import (
    GraspLiftConfig, RandomizationConfig, benchmark_config, hidden_entries, ramp_randomization,
)
from ..physics.device_layout import Precision
from ..physics.config import (
    MAX_ENVS, RECORD_CONFIG, Bool, ConfigError, Int, NonNegative, Positive, Real, Str, check_range, config_dataclass,
    from_dict, builtin_config, read_extending_yaml, replace,
)
from .controllers import Controller, check_controller_spec, controller_of, residual_bases, spec_forms
from .protocol import DEMONSTRATION_SEED_OFFSET, VALIDATION_SEED_OFFSET, check_not_sealed

PositiveInt = Annotated[Int, Ge(1)]
Unit = Annotated[Real, Ge(0), Le(1)]
_Scale = Annotated[Real, Ge(0), Le(2)]


@with_config(RECORD_CONFIG)
class PPOKwargs(TypedDict, total=False):
    """Keyword arguments of SB3's PPO that a training config may set (only the keys given are passed;
    SB3's defaults fill the rest). A test checks that every key is an argument of ``PPO.__init__``."""

    learning_rate: Positive
    n_steps: PositiveInt
    batch_size: PositiveInt
    n_epochs: PositiveInt
    gamma: Unit
    gae_lambda: Unit
    clip_range: Positive
    clip_range_vf: Positive | None
    normalize_advantage: Bool
    ent_coef: NonNegative
    vf_coef: NonNegative
    max_grad_norm: Positive
    use_sde: Bool
    #: -1: sample the gSDE noise matrix once per rollout
    sde_sample_freq: Annotated[Int, Ge(-1)]
    target_kl: Positive | None
    stats_window_size: PositiveInt


@with_config(RECORD_CONFIG)
class SACKwargs(TypedDict, total=False):
    """Keyword arguments of SB3's SAC that a training config may set (see :class:`PPOKwargs`)."""

    learning_rate: Positive
    buffer_size: PositiveInt
    learning_starts: Annotated[Int, Ge(0)]
    batch_size: PositiveInt
    tau: Annotated[Real, Gt(0), Le(1)]
    gamma: Unit
    #: updates every n steps, or [n, "step" | "episode"]
    train_freq: PositiveInt | tuple[PositiveInt, Literal["step", "episode"]]
    #: -1: as many gradient steps as environment steps in the rollout
    gradient_steps: Annotated[Int, Ge(-1)]
    optimize_memory_usage: Bool
    n_steps: PositiveInt
    #: a number, "auto" or "auto_<initial value>"
    ent_coef: Positive | Str
    target_update_interval: PositiveInt
    target_entropy: Real | Str
    use_sde: Bool
    sde_sample_freq: Annotated[Int, Ge(-1)]
    use_sde_at_warmup: Bool
    stats_window_size: PositiveInt


@config_dataclass
class TrainConfig:
    """A training run (hyper-parameters are passed to the SB3 algorithm as given).

    These defaults are PPO from scratch on the task's own randomisation: ``configs/train/ppo_scratch.yaml`` spells
    the same values out (a test checks that both agree). The default run, ``configs/train/ppo.yaml``
    (:func:`default_training`), extends it.
    """

    algo: Literal["ppo", "sac"] = "ppo"
    total_timesteps: PositiveInt = 900_000
    #: 32 batched envs: the physics runs 1.6x more agent steps/s per core than at 16 (SIMD across tissues)
    n_envs: Annotated[Int, Ge(1), Le(MAX_ENVS)] = 32
    #: the training env's tissue arrays (``Simulation(precision=...)``): "float64" or "float32", an option for the
    #: speed of the rollouts (docs/performance.md, "float32 on the CPU"). Validation, model selection and every
    #: evaluation run float64, the physics the results are about, whatever this says
    precision: Precision = "float64"
    seed: Int = 0
    checkpoint_every: PositiveInt = 25_000
    torch_threads: PositiveInt = 1
    policy_net: Annotated[tuple[PositiveInt, ...], MinLen(1)] = (64, 64)
    #: PPO only: initial log standard deviation of the action noise. With gSDE (ppo.use_sde, the default)
    #: the noise is exp(log_std) times the policy's latent features (-2 is the SB3 zoo's gSDE setting; -1
    #: measured: with -2 seed 0 never learned low friction, with -1 it held 100% at every validation mu).
    #: Without gSDE, SB3's default 0 is a standard deviation of 1 in action units.
    log_std_init: Annotated[Real, Ge(-5), Le(1)] = -1.0
    #: PPO with gSDE: squash the policy's actions with tanh (SB3 ``squash_output``) instead of clipping them
    #: to [-1, 1]. A clipped Gaussian whose mean has drifted past a bound always acts at the bound, so its
    #: return no longer depends on the mean there and nothing pulls it back (a set-point "stuck" at 5 N while
    #: the jaws close); through tanh the mean keeps a gradient. SAC squashes always (this field is ignored).
    squash_actions: Bool = True
    #: behaviour-cloning warm start: a controller spec ('reactive', 'fixed', ...) whose actions the policy
    #: imitates before RL. None (the default): PPO learns from scratch.
    bc_teacher: Str | None = None
    #: environment steps of teacher demonstrations
    bc_steps: PositiveInt = 32_768
    bc_epochs: Annotated[Int, Ge(0)] = 40
    #: log standard deviation of the policy's action noise after cloning (exploration around the teacher)
    bc_log_std: Real = -1.2
    #: also fit the critic to the teacher's discounted returns during cloning (see :func:`behaviour_clone`)
    bc_value_fit: Bool = False
    #: set by ``msdgrasp clone`` (agents/offline.py): the Minari dataset the model was cloned from, without RL
    bc_dataset: Str | None = None
    #: warm start: a trained model (an SB3 ``.zip`` of the same algorithm, observation and action spaces and
    #: network) whose weights (actor, critic, action noise) this run starts from instead of random ones; the
    #: optimiser and the step count start afresh. ``{seed}`` in the path is replaced by ``seed``, so that
    #: ``--seeds 0-4`` fine-tunes each seed of an earlier run. None (the default): from scratch.
    init_model: Str | None = None
    #: model selection: at every checkpoint and at the end the policy runs ``validation_episodes`` episodes
    #: at each friction in ``validation_mu`` (seeds disjoint from ``msdgrasp evaluate``'s); the best (highest
    #: success rate, then lowest mean peak pinch) is kept as ``best_model.zip``. 0 disables it.
    validation_episodes: Annotated[Int, Ge(0)] = 6
    validation_mu: Annotated[tuple[Annotated[Real, Ge(0), Le(2)], ...], MinLen(1)] = (0.2, 0.3, 0.5, 0.7, 0.9)
    #: early stopping: the training ends once this many validations in a row have not beaten the best one (the key
    #: above), instead of running on to total_timesteps. The learning-rate schedule and the randomisation ramp still
    #: count to total_timesteps, so a stopped run is the full run's beginning, step for step, and ships its best
    #: model unless a later checkpoint would have beaten it. None: every run goes to total_timesteps.
    validation_patience: PositiveInt | None = None
    #: learning-rate schedule: "constant", or "linear" (from the algorithm's learning_rate down to 0 at
    #: total_timesteps; a resumed run anneals over the steps that remain)
    lr_schedule: Literal["constant", "linear"] = "linear"
    #: PPO only: the critic also sees the privileged entries of the observation (mu, stiffness and mass
    #: scales, node displacements); the actor does not (agents/networks.py). Needs env.privileged_obs.
    asymmetric_critic: Bool = True
    #: observation entries the actor does not see either (names of envs.task.OBS_NAMES, or a per-jaw group such
    #: as normal_force), e.g. the force readings, so that a policy cannot lean on a noisy or biased sensor; the
    #: critic still sees them. Needs asymmetric_critic (the actor's mask). Empty: the actor sees every task entry
    actor_hidden: tuple[Str, ...] = ()
    #: privileged entries the actor sees too (names of envs.core.ACTOR_PRIVILEGED: ``mu``; ``perturbations``, the
    #: episode's robustness draws, with env.privileged_perturbations): a diagnosis, an actor that knows what a
    #: deployed one would have to estimate. Needs asymmetric_critic. Empty (the default): none
    actor_privileged: tuple[Literal["mu", "perturbations"], ...] = ()
    #: residual policy (agents/residual.py): the model's action is a correction added to this controller's,
    #: clip(controller + residual_scale x model, -1, 1), in training and wherever the model runs; the controller
    #: needs the task's interface (slipfeedback: a force set-point and a pull speed). A controller registered as a
    #: residual base (slipfeedback, reactive, fixed), with its settings too (``slipfeedback:initial=0.7,gain=0.8,
    #: pull=0.25``, the policy spec of ``msdgrasp evaluate``). None: the model acts alone
    residual_base: Str | None = None
    #: the largest correction, in action units (the action range is [-1, 1]): one for both actions, or one per
    #: action (jaw, pull); 0 leaves that action to the controller
    residual_scale: Annotated[Real, Gt(0), Le(2)] | tuple[_Scale, _Scale] = 0.5
    #: how the correction acts: "add" (both ways: clip(controller + scale x model, -1, 1)) or "raise" (only up:
    #: clip(controller + scale x max(model, 0), -1, 1)), so the policy can add grip where the controller's is
    #: too light but never take away the grip the controller holds the grasps with
    residual_mode: Literal["add", "raise"] = "add"
    #: when the correction acts: "reset" (from each episode's first step) or "pull" (from the step a slip-feedback
    #: controller starts its pull; before it, the controller's action alone, so a friction estimator reads the
    #: closing at its own probe grip)
    residual_start: Literal["reset", "pull"] = "reset"
    #: the PPO block replaces SB3's defaults key by key (a key left out gets SB3's default, not this one's)
    ppo: PPOKwargs = field(default_factory=lambda: PPOKwargs(
        learning_rate=1e-3, n_steps=128, batch_size=1024, n_epochs=10, gamma=0.999, gae_lambda=0.95,
        clip_range=0.2, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5, use_sde=True, sde_sample_freq=4,
    ))
    sac: SACKwargs = field(default_factory=lambda: SACKwargs(
        learning_rate=3e-4, buffer_size=200_000, batch_size=256, gamma=0.99, tau=0.005, learning_starts=2000,
        train_freq=1, gradient_steps=1,
    ))
    #: the training task: the benchmark task msdgrasp/GraspLift-v2 (envs.core.benchmark_config: every observation
    #: entry from a named sensor, friction drawn log-uniformly, a pinch action that spends more of its range on light
    #: grips, a pull-speed action, a peak-pinch charge scaled by mu / 0.4; docs/design.md), plus the privileged
    #: entries the critic reads
    env: GraspLiftConfig = field(default_factory=lambda: replace(benchmark_config(), privileged_obs=True))
    #: domain randomisation of the training: the training's episodes (and its validation episodes, which select
    #: the model) are drawn from this in place of env.randomization; the model's task stays ``env`` (evaluations
    #: and the robustness suite run on it). None: env.randomization
    train_randomization: RandomizationConfig | None = None
    #: a curriculum: (start, end) fractions of total_timesteps over which the training's randomisation moves
    #: linearly from env.randomization to train_randomization (envs.core.ramp_randomization); before start the
    #: episodes are env's. None: train_randomization from the first step
    randomization_ramp: tuple[Unit, Unit] | None = None

    def init_model_path(self) -> Path | None:
        """``init_model`` with ``{seed}`` replaced by this run's seed (None without a warm start)."""
        return None if self.init_model is None else Path(self.init_model.replace("{seed}", str(self.seed)))

    def check_inputs(self) -> None:
        """ConfigError for a file the run reads that is not there (the warm start's model), before it writes."""
        init = self.init_model_path()
        if init is not None and not init.is_file():
            raise ConfigError(f"init_model: {init} is not a file (a trained model's .zip, e.g. <run>/best_model.zip)")

    def training_task(self, progress: float = 1.0) -> GraspLiftConfig:
        """The task the training draws its episodes from after a fraction ``progress`` of total_timesteps (the
        curriculum's level then); 1.0: the task it validates on."""
        if self.train_randomization is None:
            return self.env
        level = 1.0
        if self.randomization_ramp is not None:
            lo, hi = self.randomization_ramp
            level = 1.0 if progress >= hi else max(0.0, (progress - lo) / (hi - lo))
        return replace(self.env, randomization=ramp_randomization(self.env.randomization, self.train_randomization,
                                                                  level))

    def seed_sets(self) -> list[tuple[int, int, str]]:
        """Every run of reset seeds the training derives from ``seed``: (first, count, how): the training envs (and the
        networks' initialisation), the validation episodes and behaviour cloning's demonstrations."""
        sets = [(self.seed, self.n_envs, f"training envs: seed + i, i < n_envs = {self.n_envs}")]
        if self.validation_episodes:
            sets.append((self.seed + VALIDATION_SEED_OFFSET, self.validation_episodes,
                         f"validation episodes: seed + {VALIDATION_SEED_OFFSET} + i, i < validation_episodes = "
                         f"{self.validation_episodes}"))
        if self.bc_teacher is not None:
            sets.append((self.seed + DEMONSTRATION_SEED_OFFSET, self.n_envs,
                         f"demonstrations: seed + {DEMONSTRATION_SEED_OFFSET} + i, i < n_envs = {self.n_envs}"))
        return sets

    def __post_init__(self) -> None:
        for first, count, via in self.seed_sets():  # (a training never draws the sealed evaluation episodes)
            check_not_sealed(first, count, "seed", value=self.seed, via=via)
        if self.validation_patience is not None and self.validation_episodes == 0:
            raise ConfigError(f"validation_patience: {self.validation_patience} needs validation_episodes >= 1 (it "
                              "counts validations), got validation_episodes 0; set validation_patience: null")
        _check_critic(self)
        if self.squash_actions and self.algo == "ppo" and not self.ppo.get("use_sde", False):
            raise ConfigError("squash_actions: true needs ppo.use_sde: true (SB3 squashes gSDE actions only); "
                              "set squash_actions: false to train PPO without gSDE")
        _check_residual(self)
        if self.bc_teacher is not None:
            _check_teacher(self.bc_teacher, self.env)
        if self.init_model is not None and self.bc_teacher is not None:
            raise ConfigError("give either init_model (start from a trained model) or bc_teacher (clone a teacher "
                              "first), not both")
        if self.randomization_ramp is not None:
            _check_ramp(self)

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        """The training config at ``path``, strictly; ``extends:`` builds it on another file
        (:func:`~msdgrasp.physics.config.read_extending_yaml`)."""
        return from_dict(cls, read_extending_yaml(path), where=Path(path).name)


def _check_critic(config: TrainConfig) -> None:
    """The actor's and the critic's inputs: what the actor hides or sees beyond the task needs the asymmetric critic
    (its mask), which needs PPO and the privileged entries."""
    if config.actor_hidden:
        if not config.asymmetric_critic:
            raise ConfigError("actor_hidden needs asymmetric_critic: true (the actor's mask hides the entries)")
        hidden_entries(config.actor_hidden)
    if config.actor_privileged and not config.asymmetric_critic:
        raise ConfigError("actor_privileged needs asymmetric_critic: true (the actor's mask shows the entries)")
    if "perturbations" in config.actor_privileged and not config.env.privileged_perturbations:
        raise ConfigError("actor_privileged: 'perturbations' needs env.privileged_perturbations: true (the "
                          "entries it shows)")
    if config.asymmetric_critic and config.algo != "ppo":
        raise ConfigError(f"asymmetric_critic is implemented for algo 'ppo' only, got algo {config.algo!r}")
    if config.asymmetric_critic and not config.env.privileged_obs:
        raise ConfigError("asymmetric_critic: true needs env.privileged_obs: true (the critic's extra inputs)")


def _check_teacher(teacher: str, env: GraspLiftConfig) -> None:
    """A behaviour-cloning teacher is a controller spec whose grip the task's jaw can command, or a model file."""
    if controller_of(teacher) is not None:
        check_controller_spec(teacher, env)
    elif not Path(teacher).is_file():
        raise ConfigError(f"bc_teacher: {teacher!r} is neither a controller spec (e.g. 'reactive', 'fixed:2') nor a "
                          "model file")


def _residual_controller(config: TrainConfig) -> Controller:
    """The controller ``residual_base`` names, its settings checked (a friction estimator's file loads) and its
    interface on the task; ConfigError naming the field."""
    base = config.residual_base
    if config.bc_teacher is not None:
        raise ConfigError("give either residual_base (learn a correction on a controller) or bc_teacher "
                          "(clone a controller first), not both")
    entry = controller_of(base)
    if entry is None or not entry.residual_base:
        raise ConfigError(f"residual_base = {base!r} is not a controller a residual may correct; choose one of "
                          f"{', '.join(spec_forms(residual_bases()))}")
    try:
        check_controller_spec(base, config.env)
    except ConfigError as exc:
        raise ConfigError(f"residual_base: {exc}") from None
    if not entry.runs_on(config.env):
        raise ConfigError(f"residual_base: {entry.name} needs env.jaw_action: force and env.pull_action: "
                          f"forward_speed, got {config.env.jaw_action!r} / {config.env.pull_action!r}")
    return entry


def _check_residual(config: TrainConfig) -> None:
    """``residual_base`` a controller a residual may correct, and ``residual_start: pull`` one that reports when its
    pull starts."""
    entry = _residual_controller(config) if config.residual_base is not None else None
    if config.residual_start == "pull" and not (entry is not None and entry.reports_pull):
        able = " or ".join(e.shown for e in residual_bases() if e.reports_pull)
        raise ConfigError(f"residual_start: pull needs a {able} residual_base (the controller whose pull "
                          f"starts the correction), got residual_base {config.residual_base!r}")


def _check_ramp(config: TrainConfig) -> None:
    """The curriculum ramps from env.randomization to train_randomization, whose stiffness and mass ranges size the
    training env's substeps: they must cover the start's."""
    if config.train_randomization is None:
        raise ConfigError("randomization_ramp needs train_randomization (the randomisation it ramps to)")
    check_range("randomization_ramp[1]", config.randomization_ramp[1], config.randomization_ramp[0], None,
                lo_inclusive=False)
    start, end = config.env.randomization, config.train_randomization
    if end.stiffness_scale_range[1] < start.stiffness_scale_range[1]:
        raise ConfigError(f"train_randomization.stiffness_scale_range[1] = {end.stiffness_scale_range[1]!r} "
                          f"must be >= env.randomization's {start.stiffness_scale_range[1]!r}, where "
                          "randomization_ramp starts")
    if end.mass_scale_range[0] > start.mass_scale_range[0]:
        raise ConfigError(f"train_randomization.mass_scale_range[0] = {end.mass_scale_range[0]!r} must be <= "
                          f"env.randomization's {start.mass_scale_range[0]!r}, where randomization_ramp starts")


#: the built-in config of the default run (``msdgrasp train`` without ``--config``)
DEFAULT_TRAINING = "train/ppo.yaml"


def default_training() -> TrainConfig:
    """The default training run (``configs/train/ppo.yaml``: a learned correction on the slip-feedback controller with
    the built-in friction estimate, under the robustness perturbations). :class:`TrainConfig`'s own defaults are PPO
    from scratch on the task's randomisation (``configs/train/ppo_scratch.yaml``), which it extends."""
    return TrainConfig.load(builtin_config(DEFAULT_TRAINING))
