"""Gymnasium environments: ``msdgrasp/GraspLift-v2`` (spleen) and ``msdgrasp/GraspLiftSphere-v2``, the benchmark
task; ``-v1``, the same task whose actor read the truth; ``-v0``, the first interface."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode, VectorEnv

from ..physics.config import ConfigError, require_extra
from .core import BENCHMARK_VERSION, OBS_NAMES, GraspLiftConfig, GraspLiftCore


def env_config(config: GraspLiftConfig | dict | None, **overrides: Any) -> GraspLiftConfig:
    """The task config an env is built with: ``config`` (None: the defaults; a dict: its fields) with ``overrides``
    changing fields by name (ConfigError naming a bad one)."""
    from ..physics.config import from_dict, to_dict

    if config is None:
        config = GraspLiftConfig()
    elif isinstance(config, dict):
        config = from_dict(GraspLiftConfig, config, where="env")
    if overrides:
        config = from_dict(GraspLiftConfig, {**to_dict(config), **overrides}, where="env")
    return config


#: the render modes the env classes offer (rgb_array: headless frames, :mod:`.render`)
RENDER_MODES = ("rgb_array",)


def check_render_mode(render_mode: str | None, env: str) -> str | None:
    """``render_mode`` if it is one the envs can render (or None); a one-line ValueError otherwise."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"{env}: render_mode must be one of {list(RENDER_MODES)} or None, got {render_mode!r}")
    if render_mode == "rgb_array":  # a missing renderer fails at construction, not at the first render()
        require_extra("viz", f"{env}: render_mode='rgb_array'", "matplotlib")
    return render_mode


def env_info(infos: dict[str, Any], i: int) -> dict[str, Any]:
    """Env i's step info as a single env reports it (Python scalars; the reward terms as a dict; ``error`` after a
    numerical failure), from the core's batched infos. The vector env builds its infos from these, so both agree."""
    # (ndarray.item(i): the Python scalar of v[i].item() in one call)
    info = {k: ({kk: float(vv.item(i)) for kk, vv in v.items()} if isinstance(v, dict)
                else v.item(i) if isinstance(v, np.ndarray) else v[i]) for k, v in infos.items()}
    if info["numerical_failure"]:
        info["error"] = ("numerical failure: the tissue state became non-finite (blow-up) or a tet inverted "
                         f"(min volume ratio {info['min_volume_ratio']:.3g}); episode terminated")
    return info


def _batched_info(infos: dict[str, Any], rows: np.ndarray) -> dict[str, Any]:
    """The vector info that Gymnasium's ``VectorEnv._add_info`` builds from :func:`env_info` of the envs ``rows``
    (a (B,) mask), from the core's batched infos at once: each key's array in the dtype of its Python scalars
    (float64, bool, int64), zero where ``rows`` is False, with its ``_key`` mask; the reward terms nested."""
    out: dict[str, Any] = {}
    for key, value in infos.items():
        if isinstance(value, dict):
            out[key] = _batched_info(value, rows)
        else:
            kind = value.dtype.kind
            array = value.astype(np.bool_ if kind == "b" else np.int64 if kind in "iu" else np.float64)
            array[~rows] = 0
            out[key] = array
        out[f"_{key}"] = rows.copy()
    return out


def _sensor_seed(options: dict[str, Any] | None, seed: Any) -> tuple[dict[str, Any], int]:
    """The reset options without ``sensor_seed`` and its value (0 when absent): the seed of the sensors' noise stream
    apart from the physics' (``sensed_task_state``), so that one physics seed can be read through other noise."""
    options = dict(options or {})
    value = options.pop("sensor_seed", 0)
    if value != 0 and seed is None:
        raise ConfigError("reset options['sensor_seed'] needs a seed: reset(seed=..., options={'sensor_seed': k})")
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ConfigError(f"reset options['sensor_seed'] must be an integer >= 0, got {value!r}")
    return options, int(value)


def _require_reset(env: Any) -> None:
    """Refuse a step before the first reset (the episode state, mu and the random streams are set there)."""
    if not env._has_reset:
        raise ResetNeeded(f"{type(env).__name__}: step() before the first reset(); call reset() first")


def checked_action(action: Any, batch: int | None) -> np.ndarray:
    """``action`` as float64, shape (2,) (``batch`` None) or (batch, 2); ValueError on another shape or a non-finite
    entry."""
    a = np.asarray(action, dtype=np.float64)
    shape = (2,) if batch is None else (batch, 2)
    if a.shape != shape:
        raise ValueError(f"action must have shape {shape} (jaw closing, pull), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"action contains NaN or inf: {a.tolist()}")
    return a


class GraspLiftEnv(gym.Env):
    """Grasp the spleen's inferior pole with a three-jaw grasper and lift it without slipping.

    The spleen (nonlinear viscoelastic mass-spring-damper tissue) hangs from its hilum under gravity.
    The grasper starts with open jaws around the inferior pole (pose randomised by a few mm and
    degrees). Friction between jaws and tissue is Coulomb stick/slip with a coefficient mu drawn per
    episode and hidden from the agent, which must read its force sensors. Physics runs at 1 kHz
    (plus stability substeps); the agent acts every 33 physics steps (33 ms, 30.3 Hz).

    ## Action space: ``Box(-1, 1, (2,), float32)``

    What the actions command is selectable (``GraspLiftConfig.jaw_action`` / ``pull_action``):

    | index | default (``jaw_action="force"``, ``pull_action="travel"``) | alternative (``"speed"``) |
    |---|---|---|
    | 0 | pinch-force set-point ((a + 1) / 2) ** p x ``max_pinch_force_N`` (0-5 N) | jaw closing speed a x 4 mm/s |
    | 1 | pull-distance set-point (a + 1) / 2 x ``max_travel_m`` (0-60 mm) | pull speed a x 20 mm/s |

    p = ``pinch_action_exponent``. The jaw motor's 1 kHz force loop tracks the pinch-force set-point (closing
    speed = 0.02 m/s per N of error, at most ``max_closing_speed_m_s``), the arm the pull-distance set-point at up
    to ``max_pull_speed_m_s`` (20 mm/s). With ``jaw_action="speed"`` a > 0 closes; ``pull_action="forward_speed"``
    pulls at (a + 1) / 2 x 20 mm/s.

    Values outside [-1, 1] are clipped; NaN/inf or a wrong shape raises ``ValueError``. So action 0 is a
    2.5 N grip and a 30 mm lift target, and -1 is "jaws relaxed, grasper at its start".

    ``msdgrasp train`` uses ``pinch_action_exponent=2`` (action 0: a 1.25 N grip; half of the action range
    covers 0-1.25 N) and ``pull_action="forward_speed"`` (action 0: pull at 10 mm/s): measured, PPO then
    learns light, friction-dependent grips (docs/design.md). Rewards do not depend on the interface.

    ## Observation space: ``Box(-inf, inf, (32 x obs_history,), float32)`` (+ privileged, optional)

    One frame (``OBS_NAMES``); with ``obs_history = k`` the last k frames are concatenated, oldest first. Every entry
    is what a named sensor gives (:data:`.sensors.SENSORS`, the noise models below; :data:`.sensors.ENTRY_SENSORS`,
    checked by tests/test_sensors.py). From v2 (``sensed_task_state``) the task-state entries 22-27 and 31 are computed
    from the sensed values; in v0 and v1 they are the simulation's truth (no grasper senses them).

    | index | observation | sensor (v2) | scaling |
    |---|---|---|---|
    | 0 | jaw opening (R - R_min) / (R_start - R_min) | jaw_encoder | 1 = open, 0 = closed |
    | 1 | jaw closing speed | jaw_encoder | / max closing speed |
    | 2 | grasper pull distance (travel) | arm_encoder | / lift target |
    | 3 | grasper pull speed | arm_encoder | / max pull speed |
    | 4-6 | normal force of jaw 0, 1, 2 | force | / reference force (5 N) |
    | 7-9 | tangential force magnitude of jaw 0, 1, 2 | force | / reference force |
    | 10-12 | contact nodes of jaw 0, 1, 2 | contact | / nodes on the jaw's footprint |
    | 13-15 | slip speed of the tissue under jaw 0, 1, 2 | slip | / max pull speed |
    | 16-18 | share of jaw 0, 1, 2's contact nodes that slip (incipient slip) | slip | 0-1 |
    | 19-20 | previous action | command | as given |
    | 21 | elapsed time | clock | / time limit |
    | 22 | tissue lift (v2: a tracked point's, delayed; v1: the region's true mean) | lift | / lift target |
    | 23 | hold progress: time the lift has been at the target (v1: without slip, the truth) | lift | / hold_time_s |
    | 24 | slip accumulated while the lift is at the target | lift, slip | / hold_slip_tolerance_m |
    | 25 | lag of the tissue behind the grasper (travel - lift; 0 untracked) | lift, arm_encoder | / lift target |
    | 26 | peak pinch so far (v2: of the summed normal readings; v1: the true pinch) | force | / reference force |
    | 27 | highest lift so far | lift | / lift target |
    | 28-30 | friction utilisation abs(T) / N of jaw 0, 1, 2 (<= mu while sticking) | force | ratio |
    | 31 | slip since lifting began (v2: since the travel passed lift_started_m) | slip, arm_encoder | / 2 mm |
    | 32- | privileged (``privileged_obs=True``): mu, stiffness scale, mass scale, 16 node displacements | truth | (1) |
    | 83- | privileged, v2: the truth behind 13-18, 22-27, 31 (``task.PRIVILEGED_TRUTH``) | truth | as the entry |
    | last 14 | privileged (``privileged_perturbations``): pose error, force biases, latency, gain error | truth | (2) |

    (1) as they are; the node displacements / lift target. (2) ``envs.perturbations.privileged_names()``: each about 1
    at the robustness suite's largest levels; all 0 on an unperturbed task.

    The sensors' noise models (``RandomizationConfig`` fields; v2's nominal levels in brackets):

    * jaw_encoder, arm_encoder, contact, command, clock: exact.
    * force: white Gaussian noise ``sensor_noise_N`` [0.02 N] (per episode uniform from ``sensor_noise_low_N`` where
      set), a bias per jaw and episode in +-``force_bias_N`` [0], a first-order low-pass ``force_filter_s`` [0], the
      tangential reading's noise by ``force_noise`` [magnitude].
    * slip: ``slip_sensing`` exact, with white noise ``slip_noise`` on the speed and (v2) on the share, clipped to
      [0, 1] [0.02 = 0.4 mm/s]; binary (a detector); absent (zeros).
    * lift: ``lift_sensing`` tracked, white noise ``lift_noise_m`` per frame, ``lift_delay_steps`` frames late
      [0.5 mm, 2 frames]; absent (zeros).

    The sensors' noise has its own random stream in v2: ``reset(seed=s, options={"sensor_seed": k})`` reads the same
    physics (seed s) through other noise.

    ## Rewards (each term in ``info["reward_terms"]``, weights in ``RewardConfig``)

    | term | value | scale over an episode |
    |---|---|---|
    | progress | +10 x increase of min(highest lift so far / target, 1) | 0 ... +10 (once) |
    | hold | +10 x change of the hold progress (potential-based: a hold that is lost is paid back) | 0 ... +10 |
    | slip | -0.1 per mm of jaw/tissue slip | ~0 (held) ... -4 (slid off) |
    | peak_force | on success: -50 x episode peak pinch / 5 N (options below) | -2 (0.2 N) ... -50 (5 N) |
    | success | +50 once, on success | +50 |
    | failure | -10 once, when the episode ends without success (lost grasp, damage, blow-up, time limit) | -10 |
    | setpoint_change | -w x change of the pinch set-point since the last step, N (off by default: w = 0) | 0 |
    | damage | -5 per step with peak nodal stress above ``damage_stress_pa`` (terminates) | |
    | grasp, force | off by default (shaping to a first grip for ``jaw_action="speed"``; cost per N s of pinch) | 0 |

    peak_force with ``peak_force_timing="as_made"``: the same total, charged as the peak rises, refunded without
    success; with ``peak_force_mu_ref``: times mu / mu_ref, so the charge follows the ratio to the minimal slip-free
    force ~ 1 / mu; with ``peak_force_knee``: above that many points at ``peak_force_beyond_knee`` of the slope.

    Returns (``msdgrasp evaluate --policy zero --policy idle --policy fixed --mu-grid 0.3:0.9:0.1``, 10
    episodes per mu, mean over mu; the reactive and oracle rows come with every evaluation):

    | policy | success | mean peak pinch | mean return (range over mu) |
    |---|---|---|---|
    | idle (never touch: action (-1, -1)) | 0% | 0 N | -10.0 |
    | zero (action (0, 0): 2.5 N and 30 mm from the first step) | 0% | 0.06 N | -10.1 (-10.4 ... -9.8) |
    | fixed 2.5 N (close, then pull at 10 mm/s) | 100% | 2.49 N | 45.0 (44.9 ... 45.1) |
    | slip-reactive (1.2 N, +0.3 N per sensed slip) | 100% | 1.70 N | 53.0 (41.3 ... 58.1) |
    | oracle (knows mu: minimal slip-free force + 10%) | 97% | 1.00 N | 58.5 (50.2 ... 62.9) |

    The zero action pulls away before it grips. Success therefore dominates: any success earns more than any
    failure, never touching the tissue earns the failure penalty like every other failure, and at equal success
    each newton of peak pinch costs 10 points.

    ## Episode end
    Terminated on success (grasped region lifted ``lift_target_m`` and held ``hold_time_s`` while it
    slipped less than ``hold_slip_tolerance_m``; a hold spoilt by slip starts over; and only if the tissue
    has slipped less than ``lift_slip_tolerance_m`` (2 mm) since lifting began: beyond that the lift is not
    slip-free and the episode can no longer succeed, ``info["slipped"]``), on a lost grasp after lifting
    began, on tissue damage, or on a numerical failure (a non-finite state, or with ``inverted_tet_is_failure``
    an inverted tet, min_volume_ratio <= 0; ``info["error"]`` says so; the observation
    is zeros, never NaN). Truncated at ``time_limit_s`` (10 s = 304 steps).

    ## Version history
    * v2 (``msdgrasp/GraspLift-v2``, ``GraspLiftSphere-v2``; ``benchmark_config(version=2)``): the benchmark task, the
      one the default training trains on and the results are about. Version 1's physics, actions, reward and success;
      every observation entry from a named sensor (``sensed_task_state``): the lift from a point tracked in the
      laparoscope's image (0.5 mm noise per frame, two frames late), the slip entries from a tactile slip sensor
      with noise (0.02 of the top pull speed, on the slip speed and the slipping share), and every derived entry
      (peak pinch, lift slip, hold slip, lift lag, hold progress, best lift) computed from those readings; the truth
      behind them only in the privileged entries. The sensors draw their noise from a stream of their own.
    * v1 (``msdgrasp/GraspLift-v1``, ``GraspLiftSphere-v1``; ``benchmark_config(version=1)``): the benchmark task of
      msdgrasp 0.1's results (kept loadable; its actor reads the simulation's true lift, slip and peak pinch):
      pinch action exponent 2, pull-speed
      action, a peak-pinch charge scaled by mu / 0.4, friction drawn log-uniformly from 0.2-0.9 (the measurements
      behind each are in docs/design.md); the spec states ``max_episode_steps`` (304). Physics: the volume barrier
      integrated implicitly before the contacts (no tet inverts under a 5 N pinch and held nodes stay in their
      friction cone), 3 substeps per ms on the coarse spleen. Damage at the published 330 kPa
      (:data:`.core.DAMAGE_PRESSURE_PA`, human bowel under 10 s grasps) instead of v0's unsourced 60 kPa. The jaws
      open just clear of the tissue at each episode's own pose (the jaws' reach there + 1 mm), not as wide as the
      largest placement error in the ranges needs.
    * v0: the first interface (GraspLiftConfig's defaults: linear pinch action, pull-distance set-point, plain
      peak-pinch charge, uniform friction); it runs the current physics, which changed under it (3 substeps
      instead of 2, the volume floor, then the implicit barrier) and under the start radius rule (the jaws open clear
      of each episode's own placement).

    ``info``: mu, pinch_force_N, peak_pinch_N, slip_distance_m, lifted_m, travel_m, hold_time_s,
    peak_stress_pa, contact_nodes, is_success, lost_grasp, damaged, numerical_failure (non-finite state or an
    inverted tet), min_volume_ratio (smallest tet volume / rest volume), reward_terms. ``reset(options=...)`` pins
    mu, mu_kinetic, stiffness_scale, mass_scale and the pose randomisation for evaluation.
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 30}

    def __init__(self, config: GraspLiftConfig | dict | None = None, render_mode: str | None = None, **overrides: Any):
        super().__init__()
        self.render_mode = check_render_mode(render_mode, type(self).__name__)
        self.config = env_config(config, **overrides)
        self.core = GraspLiftCore(self.config, 1)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.core.obs_dim,), np.float32)
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.config.agent_dt_s))}
        self._renderer = None
        self._has_reset = False

    @property
    def observation_names(self) -> tuple[str, ...]:
        return OBS_NAMES

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options, sensor_seed = _sensor_seed(options, seed)
        if seed is not None:
            self.core.seed(0, seed, sensor_seed)
        elif not hasattr(self, "_seeded"):
            self.core.seed(0, int(self.np_random.integers(2**63)))
        self._seeded = True
        draws = self.core.reset(0, options)
        self._has_reset = True
        return self.core.obs[0].astype(np.float32), self.core.info_at_reset(0, draws)

    def step(self, action):
        _require_reset(self)
        a = checked_action(action, None)
        obs, reward, terminated, truncated, infos = self.core.step(a[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), env_info(infos, 0)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render import render_rgb

        return render_rgb(self.core, 0)

    def close(self):
        self._renderer = None


class GraspLiftSphereEnv(GraspLiftEnv):
    """GraspLift on the spherical test sample (no anchors: the jaws must hold it against the pull)."""

    def __init__(self, config: GraspLiftConfig | dict | None = None, render_mode: str | None = None, **overrides: Any):
        overrides.setdefault("scene", "sphere")
        super().__init__(config, render_mode, **overrides)


def _per_env_options(options: dict[str, Any] | None, num_envs: int) -> list[dict[str, Any]]:
    """Reset options per sub-env: a number applies to every sub-env, a sequence gives one value per sub-env."""
    options = dict(options or {})
    for name, value in options.items():
        if isinstance(value, (list, tuple, np.ndarray)) and len(value) != num_envs:
            raise ConfigError(f"reset options[{name!r}] must be one number or {num_envs} numbers (one per env), "
                              f"got {len(value)}")
    return [{name: (value[i] if isinstance(value, (list, tuple, np.ndarray)) else value)
             for name, value in options.items()} for i in range(num_envs)]


class GraspLiftVectorEnv(VectorEnv):
    """``num_envs`` GraspLift tissues stepped together in ONE numba call per step.

    Sub-env i reset with seed s behaves exactly like a single :class:`GraspLiftEnv` reset with seed
    ``s + i``. ``reset(options=...)`` pins a value for every sub-env (``{"mu": 0.4}``) or one per sub-env (a
    sequence of ``num_envs`` values: ``{"mu": [0.2, 0.4, ...]}``).

    ``autoreset_mode``: Gymnasium's ``NEXT_STEP`` (the default: a sub-env that ended returns its last observation,
    and is reset by the next ``step``, which ignores its action and returns the new episode's first observation,
    reward 0 and the reset info) or ``SAME_STEP`` (reset within the step that ended it: its last observation and
    info in ``info["final_obs"]`` and ``info["final_info"]``). Observations, rewards, flags and infos, with their
    ``_key`` masks, are exactly those of Gymnasium's ``SyncVectorEnv`` over single :class:`GraspLiftEnv` s in the same
    mode (tests/test_env_api.py).
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 30, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, config: GraspLiftConfig | dict | None = None, render_mode: str | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, **overrides: Any):
        self.render_mode = check_render_mode(render_mode, type(self).__name__)
        modes = {m.value: m for m in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)}
        mode = modes.get(getattr(autoreset_mode, "value", autoreset_mode))
        if mode is None:
            raise ConfigError(f"autoreset_mode = {autoreset_mode!r} is not supported; choose one of {sorted(modes)}")
        self.autoreset_mode = mode
        self.metadata = {**type(self).metadata, "autoreset_mode": mode}
        self.config = env_config(config, **overrides)
        self.num_envs = int(num_envs)
        self.core = GraspLiftCore(self.config, self.num_envs)
        self.single_action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.single_observation_space = spaces.Box(-np.inf, np.inf, (self.core.obs_dim,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (self.num_envs, 2), np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.num_envs, self.core.obs_dim), np.float32)
        self._seeded = False
        self._has_reset = False
        self._autoreset = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        per_env = _per_env_options(options, self.num_envs)
        sensor_seeds = [0] * self.num_envs
        for i in range(self.num_envs):
            per_env[i], sensor_seeds[i] = _sensor_seed(per_env[i], seed)
        if seed is not None:
            seeds = list(seed) if isinstance(seed, (list, tuple)) else [int(seed) + i for i in range(self.num_envs)]
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed list must have {self.num_envs} entries, got {len(seeds)}")
            for i, s in enumerate(seeds):
                self.core.seed(i, s, sensor_seeds[i])
        elif not self._seeded:
            base = np.random.SeedSequence().entropy
            for i in range(self.num_envs):
                self.core.seed(i, int(base % (2**63)) + i)
        self._seeded = True
        info: dict[str, Any] = {}
        for i in range(self.num_envs):
            info = self._add_info(info, self.core.info_at_reset(i, self.core.reset(i, per_env[i])), i)
        self._has_reset = True
        self._autoreset[:] = False
        return self.core.obs.astype(np.float32), info

    def step(self, actions):
        _require_reset(self)
        a = checked_action(actions, self.num_envs)
        # NEXT_STEP: the sub-envs that ended last step are reset now; the physics steps the whole batch in one
        # call, so theirs is stepped too and then overwritten by the reset (which sets every part of the state),
        # with their random streams put back first: as if only reset
        pending = np.flatnonzero(self._autoreset) if self.autoreset_mode == AutoresetMode.NEXT_STEP else ()
        streams = {i: self.core.rngs[i].bit_generator.state for i in pending}
        obs, reward, terminated, truncated, infos = self.core.step(a)
        obs, reward = obs.copy(), reward.copy()
        # the envs whose info is not this step's readout (reset now, ended and reset, or failed with an error
        # message) go through Gymnasium's _add_info one by one, in their order; the rest take their entries of
        # the batched readout at once (the same keys, masks, dtypes and values; 4.5 % of a step at 64 envs,
        # msdgrasp bench env)
        special: dict[int, list[dict[str, Any]]] = {}
        for i in pending:
            self.core.rngs[i].bit_generator.state = streams[i]
            special[i] = [self.core.info_at_reset(i, self.core.reset(i))]
            obs[i] = self.core.obs[i]
            reward[i], terminated[i], truncated[i] = 0.0, False, False
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            for i in np.flatnonzero(terminated | truncated):
                special[i] = [{"final_obs": obs[i].copy(), "final_info": env_info(infos, i)},
                              self.core.info_at_reset(i, self.core.reset(i))]
                obs[i] = self.core.obs[i]
        for i in np.flatnonzero(infos["numerical_failure"]):
            special.setdefault(i, [env_info(infos, i)])
        regular = np.ones(self.num_envs, dtype=bool)
        regular[list(special)] = False
        info = _batched_info(infos, regular) if regular.any() else {}
        for i in sorted(special):
            for one in special[i]:
                info = self._add_info(info, one, int(i))
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render import render_rgb

        return np.stack([render_rgb(self.core, i) for i in range(self.num_envs)])


def _benchmark(scene: str, version: int, overrides: dict[str, Any]) -> GraspLiftConfig:
    from .core import benchmark_config

    if "config" in overrides:
        raise ValueError("the benchmark ids are a fixed task: change its fields by name (gym.make(id, "
                         "time_limit_s=5.0)), or build GraspLiftEnv(config=...) for another task")
    return env_config(benchmark_config(scene, version), **overrides)


def make_benchmark_env(scene: str = "spleen", render_mode: str | None = None, version: int = BENCHMARK_VERSION,
                       **overrides: Any) -> GraspLiftEnv:
    """``msdgrasp/GraspLift-v<version>`` / ``GraspLiftSphere-v<version>``: :class:`GraspLiftEnv` on the benchmark task
    (:func:`.core.benchmark_config`); keyword arguments change its fields by name."""
    return GraspLiftEnv(_benchmark(scene, version, overrides), render_mode)


def make_benchmark_vector_env(num_envs: int = 1, scene: str = "spleen", render_mode: str | None = None,
                              autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
                              max_episode_steps: int | None = None, version: int = BENCHMARK_VERSION,
                              **overrides: Any) -> GraspLiftVectorEnv:
    """The benchmark ids' vector entry point: :class:`GraspLiftVectorEnv` on the benchmark task. ``max_episode_steps``
    (which ``gym.make_vec`` passes from the spec) must be the task's own limit: change ``time_limit_s`` instead."""
    env = GraspLiftVectorEnv(num_envs, _benchmark(scene, version, overrides), render_mode, autoreset_mode)
    if max_episode_steps is not None and int(max_episode_steps) != env.config.max_episode_steps:
        raise ValueError(f"max_episode_steps = {max_episode_steps} differs from the task's "
                         f"{env.config.max_episode_steps} (time_limit_s = {env.config.time_limit_s} s); "
                         "set time_limit_s instead")
    return env
