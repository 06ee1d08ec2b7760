"""The GraspLift task as a batched, array-in/array-out core (no Gymnasium types here).

`GraspLiftCore` owns one :class:`~msdgrasp.physics.simulation.Simulation` with ``num_envs`` tissues and
advances all of them with one numba call for the commands, one for the physics and one for the task's update
and observation per agent step; the task's per-env functions are :mod:`.task`'s, shared with the GPU core.
The single Gymnasium env is this core with ``num_envs = 1``; the vector env is the same core with
``num_envs = N``. Every sub-env has its own random
generator, so a batch reproduces N single envs seeded alike exactly.
"""

from __future__ import annotations

import math
from dataclasses import field, fields
from pathlib import Path
from typing import Annotated, Any, Literal, Sequence

import numpy as np
from annotated_types import Ge, Gt, Le, Lt

from ..physics.config import (
    Bool, ConfigError, Int, NonNegative, Positive, Real, Str, check_range, config_dataclass, from_dict,
    read_extending_yaml, replace, to_dict,
)
from ..physics.grasper import GrasperPose
from ..physics.scenario import GraspScene, sphere_scene, spleen_scene
from ..physics.device_layout import Precision
from ..physics.simulation import SUBSTEP_SAFETY, Simulation
from . import compile_helper
from .perturbations import MAX_LATENCY_STEPS, draw_columns, privileged_names
from .task import (
    D_AZIMUTH, D_KS, D_MS, D_MU, D_OFFSET_DIR, D_OFFSET_R, D_TILT, D_TILT_AXIS, MAX_LIFT_DELAY_STEPS, N_NOISE, OBS,
    OBS_NAMES, P_OFFSET, PINNABLE, PRIVILEGED_TRUTH, REWARD_TERMS, column_drawn, config_record, peak_force_weight,
    command_batch, draw_episode, noise_scales, obs_group,
    perturb_pose, pinch_setpoint, start_episode, task_params, task_state, travel_setpoint, update_batch,
)

PHYSICS_DT_S = 1e-3  # outer physics step: 1 kHz
#: the second entropy word of a sensor noise stream (v2): (seed, SENSOR_STREAM, sensor_seed)
SENSOR_STREAM = 0x5E25
#: a published damage threshold for grasped soft tissue, Pa: the safety threshold of compressive stress for human
#: small bowel and colon under 10 s grasps, 329-330 kPa (logistic regression on histological trauma; 20 samples,
#: 100-600 kPa; "Tissue stress from laparoscopic grasper use and bowel injury in humans: establishing
#: intraoperative force boundaries", BMJ Surgery, Interventions & Health Technologies 2021,
#: doi:10.1136/bmjsit-2021-000084). No such threshold is published for the spleen; the bowel's is the nearest
#: measured in humans. The benchmark task (v1) ends an episode whose peak contact pressure exceeds it;
#: evaluations report the time each episode's peak contact pressure spends above it.
DAMAGE_PRESSURE_PA = 330e3
LatencySteps = Annotated[Int, Ge(0), Le(MAX_LATENCY_STEPS)]
#: the largest grasp pose error a randomisation may draw or a reset pin: tip offset (m), axis tilt and azimuth (deg)
POSE_LIMITS = {"pose_offset_m": 0.02, "pose_tilt_deg": 30.0, "pose_azimuth_deg": 60.0}
LiftDelaySteps = Annotated[Int, Ge(0), Le(MAX_LIFT_DELAY_STEPS)]


@config_dataclass
class RewardConfig:
    """Weights of the reward terms (each term is reported in ``info["reward_terms"]``).

    The design (measured, see the README): success dominates the return; every episode without success
    pays the same failure penalty (never touching the tissue included); lift progress pays for the
    highest lift reached, so a late slip does not make an attempt worse than no attempt; and the pinch
    force is charged only *on success*, as a discount of the success bonus by the episode's peak pinch
    force. So there is no "don't touch" local optimum, and at equal success less peak pinch is strictly
    better.
    """

    #: w * increase of min(highest tissue lift so far / lift target, 1): a full lift earns w in total, once
    progress: NonNegative = 10.0
    #: potential-based: w * (phi' - phi), phi = hold progress min(hold time / hold_time_s, 1) (0 below target)
    hold: NonNegative = 10.0
    #: per mm of slip between jaws and tissue
    slip_per_mm: NonNegative = 0.1
    #: at success: -w * peak pinch force of the episode / reference force (a discount of the success bonus;
    #: 50 = 10 points per N. Measured: 25 left the learned force 10-20% higher at equal success)
    peak_force: NonNegative = 50.0
    #: when the peak-force charge is paid: "at_success" (all of it with the success bonus) or "as_made"
    #: (each rise of the episode's peak pinch is charged in the step that makes it, and the sum is refunded
    #: when the episode ends without success: the same total for every episode, paid where the force is set)
    peak_force_timing: Literal["at_success", "as_made"] = "at_success"
    #: if set, the peak-force charge per N is scaled by mu / peak_force_mu_ref (equal to the plain charge at
    #: mu = peak_force_mu_ref). The minimal slip-free force is roughly proportional to 1 / mu (Coulomb; the
    #: oracle's bisection gives F_min x mu = 0.39-0.53 N over mu 0.2-0.9), so the charge then measures the
    #: peak pinch relative to what the friction needs: an excess of 0.5 N costs 3x more at mu 0.9 than at
    #: mu 0.3, as the evaluation's ratio to the oracle counts it. None: the same charge per N at every mu.
    peak_force_mu_ref: Positive | None = None
    #: if set, the peak-force charge of an episode (points, after the friction scaling) above which it rises at
    #: ``peak_force_beyond_knee`` of its slope: a charge steep where the learned grips sit and gentler beyond, so
    #: that a steeper charge per N does not make an early heavy grip cost more than failing (at 20 points per N
    #: throughout, a 3 N grip at mu 0.9 cost 135 points and one robust seed learned never to lift). None: one slope.
    peak_force_knee: NonNegative | None = None
    #: the charge's slope beyond ``peak_force_knee``, a fraction of the slope below it (0: the knee caps the charge;
    #: a cap leaves heavier grips uncharged, and a robust training then gripped at the 5 N limit)
    peak_force_beyond_knee: NonNegative = 1.0
    #: per N of change of the pinch-force set-point from one agent step to the next (jaw_action = force; every
    #: step): a force-loop command that moves as little as the grip needs. Without it the learned policies drive
    #: the loop bang-bang (0 N and 5 N in turn), so the pinch integrates their decisions on noisy readings
    setpoint_change: NonNegative = 0.0
    #: per second of pinch force equal to the reference force (scales linearly with force; every step)
    force_per_s: NonNegative = 0.0
    #: per step in which the peak nodal stress exceeds the damage threshold
    damage: NonNegative = 5.0
    success_bonus: NonNegative = 50.0
    #: once, when an episode ends without success (lost grasp, damage, numerical failure or time limit)
    failure_penalty: NonNegative = 10.0
    #: potential-based shaping toward a first grip: w * (phi' - phi), phi = min(pinch / grasp_force_N, 1).
    #: Useful with ``jaw_action: speed`` (the jaws must be closed by the policy); the force loop of
    #: ``jaw_action: force`` closes them by itself.
    grasp: NonNegative = 0.0
    grasp_force_N: Positive = 1.0

    def peak_force_weight(self, mu: float) -> float:
        """Factor on the peak-force charge at friction ``mu``: the task's own rule (:func:`.task.peak_force_weight`)."""
        return float(peak_force_weight.py_func(config_record(self), float(mu)))


@config_dataclass
class RandomizationConfig:
    """Per-episode domain randomisation ranges (uniform). ``reset(options=...)`` can pin each value."""

    mu_range: tuple[NonNegative, NonNegative] = (0.2, 0.9)
    #: how mu is drawn from mu_range: "uniform", or "log_uniform" (uniform in log mu: low friction, the
    #: hard end of the range, comes up more often: P(mu < 0.3) = 0.27 on 0.2-0.9 instead of 0.14)
    mu_distribution: Literal["uniform", "log_uniform"] = "uniform"
    stiffness_scale_range: tuple[Positive, Positive] = (0.8, 1.2)
    mass_scale_range: tuple[Positive, Positive] = (0.9, 1.1)
    #: largest grasp pose offset: tip translation (m) and axis tilt (deg), azimuth jitter (deg)
    pose_offset_m: Annotated[Real, Ge(0), Le(POSE_LIMITS["pose_offset_m"])] = 0.001
    pose_tilt_deg: Annotated[Real, Ge(0), Le(POSE_LIMITS["pose_tilt_deg"])] = 1.0
    pose_azimuth_deg: Annotated[Real, Ge(0), Le(POSE_LIMITS["pose_azimuth_deg"])] = 1.5
    #: standard deviation of the force-sensor noise, N
    sensor_noise_N: NonNegative = 0.02
    #: the lowest noise level, N: with it, each episode draws its noise's standard deviation uniformly in
    #: [sensor_noise_low_N, sensor_noise_N] (a training that meets every sensor from this one to the noisiest);
    #: None: every episode at sensor_noise_N
    sensor_noise_low_N: NonNegative | None = None
    #: how that noise enters the tangential reading: "magnitude" (the normal reading's noise sample n added to |T| as
    #: |n|: always upward, so the tangential reading and the friction use T / N read high by 0.8 sigma on average)
    #: or "vector" (independent noise on each force component, as a three-axis load cell reads: |T + n_t|, n_t a
    #: Gaussian in the jaw face, about unbiased once |T| is a few sigma)
    force_noise: Literal["magnitude", "vector"] = "magnitude"
    #: time constant of a first-order low-pass filter on each jaw's force readings (normal and tangential, after
    #: noise and bias), s: the sensor pipeline's smoothing, which trades the noise's sigma for lag (at the 30 Hz agent
    #: rate, 0.1 s leaves 0.40 of the white noise's sigma and lags by about 0.1 s); 0: the raw readings
    force_filter_s: NonNegative = 0.0
    # ---- sensing, actuation: the robustness axes (all off by default: the nominal task)
    #: largest force-sensor bias, N: each jaw's normal-force reading is offset by a constant drawn per episode
    #: uniformly in [-bias, bias] (a load cell's zero drift)
    force_bias_N: NonNegative = 0.0
    #: what the slip sensing reports: "exact" (the slip speed and the share of slipping contact nodes per jaw),
    #: "binary" (1 where any node of the jaw slips, else 0, in both entries: a slip detector), "absent" (zeros)
    slip_sensing: Literal["exact", "binary", "absent"] = "exact"
    #: standard deviation of noise added to the slip-speed entries each step (observation units: the arm's top
    #: speed; with ``sensed_task_state`` to the slipping shares too, clipped to [0, 1]); only with slip_sensing "exact"
    slip_noise: NonNegative = 0.0
    #: what the lift tracker reports (``sensed_task_state``: the lift entries come from it): "tracked" (a point of the
    #: grasped region tracked in the laparoscope's image: the region's mean lift along the pull with noise
    #: ``lift_noise_m`` per frame and ``lift_delay_steps`` frames late) or "absent" (zeros: every entry derived from
    #: the lift, its lag behind the grasper included, is constant)
    lift_sensing: Literal["tracked", "absent"] = "tracked"
    #: standard deviation of the lift tracker's noise per frame, m
    lift_noise_m: Annotated[Real, Ge(0), Le(0.01)] = 0.0
    #: the lift tracker's delay, agent steps (image capture and tracking latency)
    lift_delay_steps: LiftDelaySteps = 0
    #: action latency in agent steps, drawn per episode uniformly from lo..hi: an action takes effect that many
    #: steps after it was sent (the jaw rests and the arm stands still until the first one arrives)
    latency_steps: tuple[LatencySteps, LatencySteps] = (0, 0)
    #: largest relative error of the jaw force loop's gain, drawn per episode uniformly in [1 - e, 1 + e]
    force_loop_gain_error: Annotated[Real, Ge(0), Lt(1)] = 0.0
    #: the jaw motor's force limit, N: set-points above it are cut to it (None: no limit below
    #: max_pinch_force_N)
    pinch_ceiling_N: Positive | None = None

    def __post_init__(self) -> None:
        for name in ("mu_range", "stiffness_scale_range", "mass_scale_range", "latency_steps"):
            lo, hi = getattr(self, name)
            check_range(f"{name}[1]", hi, lo, None)
        if self.mu_distribution == "log_uniform":
            check_range("mu_range[0] (log_uniform)", self.mu_range[0], 0.0, None, lo_inclusive=False)
        if self.sensor_noise_low_N is not None:
            check_range("sensor_noise_low_N", self.sensor_noise_low_N, 0.0, self.sensor_noise_N)


@config_dataclass
class GraspLiftConfig:
    """Everything that defines a GraspLift task (SI units)."""

    scene: Literal["spleen", "sphere"] = "spleen"
    resolution: Str | Int = "coarse"
    tissue_config: Str | None = None
    grasper_config: Str | None = None
    #: total stiffness of the compliant hilum anchors (vessels, ligaments), N/m; None = rigid anchors
    anchor_stiffness_n_per_m: Positive | None = 8.0
    #: how far the jaws reach over the inferior pole from its tip, m (None: the jaw length)
    grasp_depth_m: Real | None = 0.035
    #: physics steps (1 ms) per agent step: 33 -> 30.3 Hz agent rate
    physics_steps_per_action: Annotated[Int, Ge(1), Le(1000)] = 33
    #: fraction (0-1] of the stability limit a physics substep uses: the library's rule
    #: (physics.simulation.SUBSTEP_SAFETY, 0.5: 3 substeps on the coarse spleen), where the grasp readouts are
    #: converged (pull force within 0.01 N and slip within 0.003 mm of 15 substeps under a 2.5 N pinch; 2
    #: substeps gave errors of 0.05 N of 0.24 N and 0.95 mm)
    substep_safety: Annotated[Real, Gt(0), Le(1)] = SUBSTEP_SAFETY
    #: end an episode as a numerical failure when a tet inverts (info["min_volume_ratio"] <= 0; it is reported
    #: either way). With the spleen's volume barrier (configs/tissue/spleen.yaml) no tet inverts under the
    #: env's largest pinch, so on the defaults this flags a real failure of the physics, not a hard pinch.
    inverted_tet_is_failure: Bool = True
    #: what action[0] commands: "force" = a pinch-force set-point in [0, max_pinch_force_N] that the jaw
    #: motor's 1 kHz force loop tracks (a torque-controlled jaw); "speed" = the jaw closing speed
    jaw_action: Literal["force", "speed"] = "force"
    #: what action[1] commands: "travel" = a pull distance set-point in [0, max_travel_m] that the arm's
    #: position loop tracks (speed-limited); "speed" = the pull speed in [-1, 1] x the arm's top speed;
    #: "forward_speed" = the pull speed in [0, 1] x the top speed (action -1: stand still, 0: half speed)
    pull_action: Literal["travel", "speed", "forward_speed"] = "travel"
    #: largest pinch-force set-point (jaw_action = force), N
    max_pinch_force_N: Annotated[Real, Gt(0), Le(50)] = 5.0
    #: shape of the pinch-force action: set-point = ((a + 1) / 2) ** p x max_pinch_force_N. p = 1 is linear
    #: (action 0: half the largest force); p = 2 spends more of the action range on light grips (action 0:
    #: a quarter of it, 1.25 N at 5 N)
    pinch_action_exponent: Annotated[Real, Ge(1), Le(4)] = 1.0
    #: shape of the forward-speed pull action (pull_action = forward_speed): speed = ((a + 1) / 2) ** q x the top
    #: speed. q = 1 is linear (action 0: half the top speed, 10 mm/s); q = 2 spends more of the action range on slow
    #: pulls (action 0: a quarter of it, 5 mm/s), where a grasp needs less grip (the oracle's minimal force: 0.81-0.83x
    #: that of a 10 mm/s pull at mu 0.3-0.8; docs/design.md)
    pull_action_exponent: Annotated[Real, Ge(1), Le(4)] = 1.0
    #: gain of the 1 kHz force loop: closing speed per newton of force error, m/s/N (limited to the
    #: grasper's max closing speed)
    force_loop_gain_m_s_per_N: Annotated[Real, Gt(0), Le(1)] = 0.02
    #: largest pull-distance set-point (pull_action = travel), m
    max_travel_m: Annotated[Real, Gt(0), Le(0.2)] = 0.06
    #: the arm's pull-speed limit, m/s: the travel loop's top speed and the scale of a speed action
    #: (None: the grasper config's max_pull_speed_m_s)
    max_pull_speed_m_s: Annotated[Real, Gt(0), Le(0.1)] | None = None
    #: observation frames stacked (oldest first); 1 = the current frame only
    obs_history: Annotated[Int, Ge(1), Le(16)] = 1
    #: lift (pull) of the grasped tissue that counts as success, m
    lift_target_m: Annotated[Real, Gt(0), Le(0.2)] = 0.03
    #: the lift must be held this long, without slip, s
    hold_time_s: NonNegative = 1.0
    #: slip tolerated during the hold, m (sensor resolution); a hold with more slip starts over
    hold_slip_tolerance_m: NonNegative = 0.5e-3
    #: slip tolerated from the moment lifting began (lift >= lift_started_m) to the end: beyond it the
    #: lift is not slip-free and the episode cannot succeed any more, m. It does NOT end the episode:
    #: measured, ending it made an early slip cost more than never touching (a -10 now vs a discounted
    #: -10 at the time limit), and 1 of 5 PPO seeds settled on never touching the tissue
    lift_slip_tolerance_m: Positive = 2e-3
    time_limit_s: Positive = 10.0
    #: pinch-force normalisation (observation and force penalty), N
    reference_force_N: Positive = 5.0
    #: peak nodal stress (contact pressure) beyond which the tissue counts as damaged, Pa. Version 0's 60 kPa is a
    #: limit of the task, not a measured threshold; the benchmark task (v1) uses the published DAMAGE_PRESSURE_PA
    damage_stress_pa: Positive = 60e3
    #: terminate when damaged
    terminate_on_damage: Bool = True
    #: lift after which losing all contact counts as a lost grasp, m
    lift_started_m: NonNegative = 0.002
    #: add privileged state (mu, scales, node displacements) to the observation
    privileged_obs: Bool = False
    #: compute the task-state entries of the observation (lift, hold progress, hold slip, lift lag, peak pinch, best
    #: lift, lift slip) from the sensors (the force sensors, the tactile slip sensor, the lift tracker, the arm's
    #: encoder) instead of the simulation's truth; the truth then joins the privileged entries (PRIVILEGED_TRUTH).
    #: Reward and success read the truth either way. True from version 2 of the benchmark task
    sensed_task_state: Bool = False
    #: nodes subsampled for the privileged displacement observation
    privileged_nodes: Annotated[Int, Ge(1)] = 16
    #: also add the episode's robustness draws to the privileged state (.perturbations.privileged_names(): pose error,
    #: force bias, latency, force-loop gain), so that a critic trained under them can tell a hard episode from a
    #: poor action. Needs privileged_obs
    privileged_perturbations: Bool = False
    reward: RewardConfig = field(default_factory=RewardConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)

    def __post_init__(self) -> None:
        if self.privileged_perturbations and not self.privileged_obs:
            raise ConfigError("privileged_perturbations: true needs privileged_obs: true (they extend its entries)")

    @property
    def agent_dt_s(self) -> float:
        return self.physics_steps_per_action * PHYSICS_DT_S

    @property
    def max_episode_steps(self) -> int:
        return int(math.ceil(self.time_limit_s / self.agent_dt_s))

    @classmethod
    def from_yaml(cls, path: str | Path) -> "GraspLiftConfig":
        """The task of the ``env:`` section of a YAML file (a training config's, e.g. configs/train/ppo.yaml),
        strictly: the section is required (no default task is assumed) and its keys are checked. The file's
        other keys are the training's, checked by the training config's loader. ``extends:`` builds the file on
        another (:func:`~msdgrasp.physics.config.read_extending_yaml`)."""
        data = read_extending_yaml(path)
        if "env" not in data:
            raise ConfigError(f"{path}: no 'env:' section; put the task's keys under env: (e.g. env: {{scene: spleen, "
                              f"privileged_obs: true}}; see configs/train/ppo.yaml)")
        if not isinstance(data["env"], dict):
            raise ConfigError(f"{path}:env must be a mapping of keys, got {data['env']!r}")
        return from_dict(cls, data["env"], where=f"{path}:env")


#: the benchmark task's versions (``msdgrasp/GraspLift-v<k>``); the latest is the one results are about
BENCHMARK_VERSIONS = (1, 2)
BENCHMARK_VERSION = BENCHMARK_VERSIONS[-1]
#: the sensors of version 2's nominal task (RandomizationConfig fields): the tactile slip sensor's noise (the arm's top
#: speed per frame: 0.02 is 0.4 mm/s), the lift tracker's noise (m per frame) and delay (frames: capture and tracking)
V2_SENSING = {"slip_noise": 0.02, "lift_noise_m": 0.5e-3, "lift_delay_steps": 2}


def benchmark_config(scene: str = "spleen", version: int = BENCHMARK_VERSION) -> GraspLiftConfig:
    """The benchmark task (``msdgrasp/GraspLift-v<version>``, ``msdgrasp/GraspLiftSphere-v<version>``).

    Version 1: its interface and reward differ from GraspLiftConfig's defaults (version 0) where the training
    measured better learning (docs/design.md): a pinch action that spends more of its range on light grips
    (exponent 2: action 0 is a 1.25 N set-point), a pull-speed action (action 0: 10 mm/s) instead of a travel
    set-point, a peak-pinch charge scaled by mu / 0.4 (it follows the ratio to the minimal slip-free force), friction
    drawn log-uniformly from 0.2-0.9 (low friction, where grasps fail, comes up more often), and tissue damage at the
    published threshold DAMAGE_PRESSURE_PA (330 kPa) instead of version 0's unsourced 60 kPa (a jaw placed 5 mm / 10
    deg off touches first with one node at about 100 kPa for a few ms, which no published measure calls damage).

    Version 2 (the results' task): version 1 whose every observation entry is what a named sensor gives
    (``sensed_task_state``, :data:`.sensors.SENSORS`): the lift from a tracked point (0.5 mm noise, two frames
    late), the slip-derived entries from a noisy tactile slip sensor, the peak pinch from the force readings; the
    truth only in the privileged entries. Physics, actions, reward and success are version 1's.

    The default training (agents.models.TrainConfig) trains on the latest, adding the privileged observations its
    critic reads (the actor does not) and its own domain randomisation."""
    if version not in BENCHMARK_VERSIONS:
        raise ConfigError(f"version must be one of {list(BENCHMARK_VERSIONS)}, got {version!r}")
    sensing = V2_SENSING if version >= 2 else {}
    return GraspLiftConfig(scene=scene, pinch_action_exponent=2.0, pull_action="forward_speed",
                           damage_stress_pa=DAMAGE_PRESSURE_PA, reward=RewardConfig(peak_force_mu_ref=0.4),
                           sensed_task_state=version >= 2,
                           randomization=RandomizationConfig(mu_distribution="log_uniform", **sensing))


def ramp_randomization(start: RandomizationConfig, end: RandomizationConfig, level: float) -> RandomizationConfig:
    """The randomisation a fraction ``level`` (0-1) of the way from ``start`` to ``end`` (a training curriculum):
    numbers and ranges linearly where both ends have them (latency bounds and counts rounded half up to whole steps),
    anything else (slip sensing, the mu distribution, a pinch ceiling that one end has not) at ``end``'s once
    ``level`` > 0."""
    level = min(max(float(level), 0.0), 1.0)
    if level == 0.0:
        return start
    values: dict[str, Any] = {}
    for f in fields(RandomizationConfig):
        a, b = getattr(start, f.name), getattr(end, f.name)
        if f.name == "sensor_noise_low_N" and (a is None or b is None):
            if b is None and (a is None or level == 1.0):
                values[f.name] = None
                continue
            # (no lowest level is every episode at the one level: the range [s, s])
            a = start.sensor_noise_N if a is None else a
            b = end.sensor_noise_N if b is None else b
        if isinstance(b, tuple) and isinstance(a, tuple):
            mixed = tuple(x + level * (y - x) for x, y in zip(a, b))
            values[f.name] = tuple(int(math.floor(v + 0.5)) for v in mixed) if f.name == "latency_steps" else mixed
        elif type(f.default) is int:  # a count (lift_delay_steps): whole steps, rounded half up
            values[f.name] = int(math.floor(a + level * (b - a) + 0.5))
        elif isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
            values[f.name] = a + level * (b - a)
        else:
            values[f.name] = b
    return RandomizationConfig(**values)


def setpoint_interface(config: GraspLiftConfig) -> bool:
    """Whether the task is commanded by a pinch-force set-point and a forward pull speed (the benchmark task's
    interface; the one the slip-feedback controller drives)."""
    return config.jaw_action == "force" and config.pull_action == "forward_speed"


def _action_of_fraction(fraction: np.ndarray | float, exponent: float) -> np.ndarray:
    """The action in [-1, 1] that commands ``fraction`` (clipped to [0, 1]) of its range: the inverse of
    :func:`.task.shaped_fraction`."""
    frac = np.clip(np.asarray(fraction, dtype=np.float64), 0.0, 1.0)
    return 2.0 * frac ** (1.0 / exponent) - 1.0


def pull_action(speed_fraction: np.ndarray | float, config: GraspLiftConfig) -> np.ndarray:
    """The pull action (pull_action = forward_speed) whose speed is ``speed_fraction`` of the arm's top speed,
    clipped to [-1, 1]: the inverse of :func:`.task.pull_speed_fraction`."""
    return _action_of_fraction(speed_fraction, config.pull_action_exponent)


def pinch_action(force_N: np.ndarray | float, config: GraspLiftConfig) -> np.ndarray:
    """The jaw action whose pinch-force set-point is ``force_N`` (jaw_action = force), clipped to [-1, 1]:
    the inverse of :func:`.task.pinch_setpoint`."""
    return _action_of_fraction(np.asarray(force_N, dtype=np.float64) / config.max_pinch_force_N,
                               config.pinch_action_exponent)


def perturbed_pose(pose: GrasperPose, draws: dict[str, Any], offset_m: float, tilt_deg: float,
                   azimuth_deg: float) -> GrasperPose:
    """The grasp pose of one episode: ``pose`` moved by the episode's random draws (``offset_dir`` and
    ``tilt_axis``: 3 standard normals each; ``offset_r`` in [0, 1]; ``tilt`` and ``azimuth`` in [-1, 1]),
    by :func:`.task.perturb_pose` (the tip moves up to ``offset_m`` normal to the axis, the axis tilts up to
    ``tilt_deg``, the jaws turn up to ``azimuth_deg``)."""
    d = np.zeros(len(draw_columns()))
    d[D_OFFSET_DIR : D_OFFSET_DIR + 3] = draws["offset_dir"]
    d[D_TILT_AXIS : D_TILT_AXIS + 3] = draws["tilt_axis"]
    d[D_OFFSET_R], d[D_TILT], d[D_AZIMUTH] = draws["offset_r"], draws["tilt"], draws["azimuth"]
    tip, axis, e1 = (np.zeros(3) for _ in range(3))
    vec = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    perturb_pose(vec(pose.tip), vec(pose.axis), vec(pose.e1), d, float(offset_m), math.radians(tilt_deg),
                 math.radians(azimuth_deg), tip, axis, e1)
    return GrasperPose(tip, axis, e1)


def hidden_entries(names: Sequence[str], field: str = "actor_hidden") -> list[int]:
    """Frame positions of the observation entries ``names`` name: an entry of :data:`OBS_NAMES`, or a per-jaw
    group's prefix (``normal_force``: its three entries). A one-line ConfigError names an unknown one."""
    groups = sorted({n.rsplit("_", 1)[0] for n in OBS_NAMES if n[-2:] in ("_0", "_1", "_2")})
    out: list[int] = []
    for name in names:
        if name in OBS:
            out.append(OBS[name])
        elif name in groups:
            out.extend(range(obs_group(name).start, obs_group(name).stop))
        else:
            raise ConfigError(f"{field}: {name!r} is no observation entry; allowed: an entry of envs.task.OBS_NAMES "
                              f"or a per-jaw group ({', '.join(groups)})")
    return sorted(set(out))


#: privileged entries an actor may be shown (``TrainConfig.actor_privileged``), by name: ``mu`` (its frame position
#: after the task entries) and ``perturbations`` (the privileged perturbation block, the frame's last entries with
#: ``privileged_perturbations``: the episode's pose error, force biases, latency and force-loop gain error)
ACTOR_PRIVILEGED = {"mu": 0, "perturbations": None}


def actor_mask(n_task: int, frame_dim: int, history: int, hidden: Sequence[str] = (),
               privileged: Sequence[str] = (), perturbations: bool = False) -> list[bool]:
    """True for the ``n_task`` task entries of each of ``history`` frames of ``frame_dim`` entries (a frame is
    the task entries, then the privileged ones an asymmetric critic sees and the actor does not), except the
    task entries ``hidden`` names (:func:`hidden_entries`), which the actor does not see either, and with the
    privileged entries ``privileged`` names (:data:`ACTOR_PRIVILEGED`), which it does. ``perturbations``: whether
    the frame ends with the privileged perturbation block (``privileged_perturbations``)."""
    if not 0 < n_task <= frame_dim:
        raise ValueError(f"n_task must be in (0, frame_dim={frame_dim}], got {n_task}")
    frame = [True] * n_task + [False] * (frame_dim - n_task)
    for i in hidden_entries(hidden):
        frame[i] = False
    n_pert = len(privileged_names())
    for name in privileged:
        if name == "perturbations":
            if not perturbations or frame_dim - n_pert < n_task:
                raise ConfigError("actor_privileged: 'perturbations' needs env.privileged_perturbations: true (the "
                                  "entries it shows)")
            frame[frame_dim - n_pert:] = [True] * n_pert
        elif name not in ACTOR_PRIVILEGED or n_task + ACTOR_PRIVILEGED[name] >= frame_dim:
            raise ConfigError(f"actor_privileged: {name!r} is no privileged entry of this observation; allowed: "
                              f"{', '.join(ACTOR_PRIVILEGED)} (with env.privileged_obs: true)")
        else:
            frame[n_task + ACTOR_PRIVILEGED[name]] = True
    return frame * history


def check_pin(name: str, value: float, sim: Simulation, mu: float = 10.0) -> None:
    """A value pinned by ``reset(options=...)`` (PINNABLE) in its range, or a one-line ConfigError; ``mu``:
    the episode's friction, the bound of mu_kinetic."""
    lo, hi = {"mu": (0.0, 10.0), "mu_kinetic": (0.0, mu), "stiffness_scale": (0.0, sim.max_stiffness_scale),
              "mass_scale": (sim.min_mass_scale, None), **{k: (0.0, v) for k, v in POSE_LIMITS.items()}}[name]
    check_range(f"options[{name!r}]", value, lo, hi, lo_inclusive=name != "stiffness_scale")


class GraspLiftCore:
    """Batched GraspLift dynamics, observations and rewards. Arrays in, arrays out.

    ``precision``: the storage of the tissue's per-node, per-spring and per-tet arrays (:class:`.Simulation`'s):
    "float64", the physics of every result and evaluation, or "float32", a learner's option for the speed of its
    rollouts (``TrainConfig.precision``, ``TorchPPOConfig.precision``; the GPU core takes the same argument)."""

    def __init__(self, config: GraspLiftConfig | None = None, num_envs: int = 1,
                 precision: Precision = "float64") -> None:
        self.config = cfg = config or GraspLiftConfig()
        self.num_envs = B = int(num_envs)
        if B < 1:
            raise ConfigError(f"num_envs must be >= 1, got {num_envs!r}")
        if cfg.grasper_config is None:
            from ..physics.config import builtin_config

            cfg = self.config = from_dict(GraspLiftConfig, {**to_dict(cfg),
                                                            "grasper_config": str(builtin_config("grasper/env.yaml"))})
        # the task's kernels compile in a helper process beside the physics' where the cache is cold; it is joined
        # before the first task kernel this core calls (which then loads what it made), stopped if this raises
        with compile_helper.beside(cfg, precision):
            self._build(cfg, B, precision)
        self._set_params()
        #: per-env episode state (:class:`.task.TaskState`); each field is also an attribute of the core
        #: (``core.mu``, ``core.lift``, ``core.obs`` ...): the same arrays, which the kernels update in place
        self.state = task_state(B, cfg.obs_history, self.frame_dim)
        self.__dict__.update(self.state._asdict())

    def _build(self, cfg: GraspLiftConfig, B: int, precision: Precision) -> None:
        """The scene, its simulation, the grasp region, the observation's size and the random streams."""
        if cfg.scene == "spleen":
            self.scene: GraspScene = spleen_scene(cfg.tissue_config, cfg.grasper_config, cfg.resolution,
                                                  insert_depth_m=cfg.grasp_depth_m,
                                                  anchor_stiffness_n_per_m=cfg.anchor_stiffness_n_per_m)
        else:
            self.scene = sphere_scene(cfg.tissue_config, cfg.grasper_config, cfg.resolution)
        rnd = self._built_randomization = cfg.randomization
        self.sim = self.scene.simulation(
            B, dt=PHYSICS_DT_S, max_stiffness_scale=max(1.0, rnd.stiffness_scale_range[1]),
            min_mass_scale=min(1.0, rnd.mass_scale_range[0]), safety=cfg.substep_safety, precision=precision,
        )
        self.precision = self.sim.precision
        g = self.scene.grasper
        self.max_close = g.max_closing_speed_m_s
        self.max_pull = g.max_pull_speed_m_s if cfg.max_pull_speed_m_s is None else cfg.max_pull_speed_m_s
        mesh = self.scene.mesh
        # grasp region: surface nodes the jaws may hold (within the jaw span), tracked for the lift
        pose = self.scene.pose
        rel = self.scene.x_start - pose.tip
        s = rel @ pose.axis
        span = (s <= 0) & (s >= -g.jaw_length_m)
        region = np.intersect1d(np.flatnonzero(span), mesh.surface_nodes)
        self.region = region if region.size else mesh.surface_nodes
        # nominal node count per jaw footprint (contact fraction normaliser)
        u = pose.jaw_directions()
        lat = np.stack([rel @ np.cross(pose.axis, u[k]) for k in range(3)], axis=1)
        near = np.stack([rel @ u[k] for k in range(3)], axis=1)
        on = span[:, None] & (np.abs(lat) <= 0.5 * g.jaw_width_m) & (near > 0)
        on &= np.isin(np.arange(mesh.n_nodes), mesh.surface_nodes)[:, None]
        self.nominal_contacts = np.maximum(on.sum(axis=0), 1).astype(np.float64)
        rng0 = np.random.default_rng(0)
        self.priv_nodes = np.sort(rng0.choice(mesh.n_nodes, size=min(cfg.privileged_nodes, mesh.n_nodes),
                                              replace=False))
        #: one observation frame; the observation is the last ``obs_history`` frames, oldest first
        self.frame_dim = len(OBS_NAMES) + (3 + 3 * len(self.priv_nodes) if cfg.privileged_obs else 0) + (
            len(PRIVILEGED_TRUTH) if cfg.privileged_obs and cfg.sensed_task_state else 0) + (
            len(privileged_names()) if cfg.privileged_perturbations else 0)
        self.obs_dim = self.frame_dim * cfg.obs_history

        self.rngs = [np.random.default_rng() for _ in range(B)]
        #: the sensors' noise streams: with ``sensed_task_state`` (v2) each env's own, seeded apart from its physics
        #: (:meth:`seed`'s ``sensor_seed``), so two envs with the same physics seed can read different noise; before
        #: v2 the physics stream itself (the streams of earlier versions unchanged)
        self.sensor_rngs = self.rngs if not cfg.sensed_task_state else [np.random.default_rng() for _ in range(B)]
        self._noise_scales = np.zeros((B, N_NOISE))

    def __getstate__(self) -> dict[str, Any]:
        """The core's state without the render cache (matplotlib figures and Agg buffers cannot be pickled);
        a copy or an unpickled core builds its own figure on its first render."""
        state = self.__dict__.copy()
        state.pop("_render_cache", None)
        return state

    def _set_params(self) -> None:
        """The task constants of the current config, and which draw columns a reset draws (once per config, not per
        reset: the kernel's rule, asked from Python)."""
        self.params = task_params(self)
        self._drawn = [bool(column_drawn(self.params, k)) for k in range(len(self.params.draw_law))]

    def set_randomization(self, randomization: RandomizationConfig) -> None:
        """Draw the episodes of later resets from ``randomization`` (a training curriculum moves it); episodes under
        way keep their draws. The ranges that sized the simulation's substeps when the core was built bound it:
        stiffness scale at most, mass scale at least theirs."""
        built = self._built_randomization
        limits = (("stiffness_scale_range[1]", randomization.stiffness_scale_range[1],
                   max(1.0, built.stiffness_scale_range[1]), "<="),
                  ("mass_scale_range[0]", randomization.mass_scale_range[0], min(1.0, built.mass_scale_range[0]), ">="))
        for name, value, bound, op in limits:
            if (value > bound) if op == "<=" else (value < bound):
                raise ConfigError(f"randomization.{name} = {value!r} must be {op} {bound!r}, the value this env was "
                                  f"built for (build it with the widest randomisation it will draw from)")
        self.config = replace(self.config, randomization=randomization)
        self._set_params()

    # ------------------------------------------------------------------------------------------
    def seed(self, index: int, seed: int | None, sensor_seed: int = 0) -> None:
        """Seed sub-env ``index``'s physics stream with ``seed`` (its draws: friction, tissue, pose, perturbations)
        and, with ``sensed_task_state``, its sensors' noise stream with (``seed``, ``sensor_seed``)."""
        check_range("sensor_seed", sensor_seed, 0, None)
        self.rngs[index] = np.random.default_rng(seed)
        if self.sensor_rngs is not self.rngs:
            self.sensor_rngs[index] = np.random.default_rng(None if seed is None else [int(seed), SENSOR_STREAM,
                                                                                      int(sensor_seed)])

    def reset(self, index: int, options: dict[str, Any] | None = None) -> dict[str, float]:
        """Reset sub-env ``index``: draw (or pin, via ``options``) friction, scales and pose."""
        options = dict(options or {})
        unknown = sorted(set(options) - set(PINNABLE))
        if unknown:
            raise ConfigError(f"reset options: unknown key(s) {unknown}; allowed: {list(PINNABLE)}")
        rnd = self.config.randomization
        rng = self.rngs[index]
        # always draw every value (keeps the random stream independent of which values are pinned)
        # (random() and standard_normal() are the variates NumPy's uniform() and normal() scale: the same stream)
        for k, (normal, drawn) in enumerate(zip(self.params.draw_is_normal, self._drawn)):
            self.draws[index, k] = (rng.standard_normal() if normal else rng.random()) if drawn else 0.0
        draw_episode(self.params, self.state, index)
        drawn = self.draws[index]
        v = {"mu": drawn[D_MU], "stiffness_scale": drawn[D_KS], "mass_scale": drawn[D_MS],
             **{name: getattr(rnd, name) for name in PINNABLE[P_OFFSET:]}, **options}
        v = {"mu_kinetic": v["mu"], **{name: float(value) for name, value in v.items()}}
        for name in PINNABLE:
            check_pin(name, v[name], self.sim, v["mu"])
        self.pin[index] = [v[name] for name in PINNABLE]
        start_episode(self.params, self.sim.kernel_state(), self.sim.kernel_readout(), self.state, index)
        return {name: v[name] for name in ("mu", "mu_kinetic", "stiffness_scale", "mass_scale")}

    # ------------------------------------------------------------------------------------------
    def step(self, actions: np.ndarray, advance: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every sub-env by one agent step. ``actions``: (B,2) in [-1,1] (clipped).

        ``advance``: the indices of the sub-envs whose physics runs this step (default: all). The others' tissues
        stand still and their task update reads their last readouts: for a batch whose ended episodes no longer
        count (an evaluation), it skips their physics and changes nothing for the rest (each tissue's physics is
        bitwise the same in any batch)."""
        actions = np.ascontiguousarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, 2):
            raise ConfigError(f"actions must have shape ({self.num_envs}, 2), got {actions.shape}")
        sim, ts = self.sim, self.state
        command_batch(self.params, sim.kernel_state(), ts, actions)
        sim.step(self.config.physics_steps_per_action, indices=advance)
        finite = sim.finite()
        volume_ratio = sim.min_volume_ratio()
        # the sensors' noise: the drawn columns in order (.task.noise_scale: one rule for both backends)
        scales = self._noise_scales
        noise_scales(self.params, ts, scales)
        for b in range(self.num_envs):
            drawn = scales[b] >= 0.0
            ts.noise[b, drawn] = scales[b, drawn] * self.sensor_rngs[b].standard_normal(int(drawn.sum()))
        update_batch(self.params, sim.kernel_state(), sim.kernel_readout(), ts, finite, volume_ratio)
        infos = {
            "mu": ts.mu.copy(),
            "pinch_force_N": ts.pinch.copy(),
            "peak_pinch_N": ts.peak_pinch.copy(),
            "slip_distance_m": ts.slip_total.copy(),
            "lifted_m": ts.lift.copy(),
            "travel_m": self.travel(),
            "hold_time_s": ts.hold_time.copy(),
            "peak_stress_pa": ts.stress.copy(),
            "contact_nodes": ts.contact.copy(),
            "is_success": ts.is_success.copy(),
            "lost_grasp": ts.lost_grasp.copy(),
            "slipped": ts.slipped.copy(),
            "lift_slip_m": ts.lift_slip.copy(),
            "damaged": ts.damaged.copy(),
            "numerical_failure": ts.numerical_failure.copy(),
            "min_volume_ratio": volume_ratio,
            "reward_terms": {name: ts.terms[:, k].copy() for k, name in enumerate(REWARD_TERMS)},
        }
        return ts.obs.astype(np.float32), ts.reward.copy(), ts.terminated.copy(), ts.truncated.copy(), infos

    # ------------------------------------------------------------------------------------------
    def pinch_setpoint(self, a: np.ndarray) -> np.ndarray:
        """Pinch-force set-point (N) of jaw action(s) ``a`` in [-1, 1] (:func:`.task.pinch_setpoint`)."""
        a = np.asarray(a, dtype=np.float64)
        return np.array([pinch_setpoint(self.params.env, x) for x in a.ravel()]).reshape(a.shape)

    def travel_setpoint(self, a: np.ndarray) -> np.ndarray:
        """Pull-distance set-point (m) of pull action(s) ``a`` in [-1, 1] (:func:`.task.travel_setpoint`)."""
        a = np.asarray(a, dtype=np.float64)
        return np.array([travel_setpoint(self.params.env, x) for x in a.ravel()]).reshape(a.shape)

    def travel(self, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Grasper pull distance along the pull direction since the episode start, m."""
        return np.einsum("bi,i->b", self.sim.g_tip[idx] - self.tip0[idx], self.params.pull_dir)

    def info_at_reset(self, index: int, draws: dict[str, float]) -> dict[str, Any]:
        return {**draws, "pinch_force_N": 0.0, "slip_distance_m": 0.0, "lifted_m": 0.0, "peak_stress_pa": 0.0,
                "is_success": False}
