"""Baseline grasp controllers, all behind one policy interface (the same one a trained model gets).

A policy maps observations to actions for a batch of episodes::

    policy.reset(infos)          # at episode start; infos: list of reset info dicts, one per episode
    actions = policy.act(obs)    # obs (B, obs_dim) -> actions (B, 2) in [-1, 1]

* :class:`FixedForcePolicy`: close until the pinch force reaches a set value, then pull while holding that
  force (a cautious surgeon: hard enough for the slipperiest tissue).
* :class:`SlipReactivePolicy`: close lightly, pull, and tighten whenever the jaw sensors show slip.
* :class:`SlipFeedbackPolicy`: start with a light grip and tighten in proportion to the slip since lifting
  began; reads no force at all, so force-sensor noise and bias do not touch it.
* :class:`OraclePolicy`: knows mu; uses the smallest fixed force that lifts without slip at that mu
  (found by bisection in simulation, cached per mu) plus a margin: the physical limit a learned policy
  is measured against.
* :class:`TorchScriptPolicy`: a torch PPO policy (:class:`.model_policy.ModelPolicy`, a Stable-Baselines3 model, lives
  apart: loading one reads its training config, :mod:`.models`, which asks this module's registry about a controller;
  a saved model is run through its learner: :func:`msdgrasp.agents.learners.learner_of_model`).

The controllers register at the end of this module (:mod:`.controller_registry`, re-exported here): a policy spec
names one by its registered name, and the rest of the package asks the registry what a controller is.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..envs.core import GraspLiftConfig, pinch_action, pull_action, setpoint_interface
from ..envs.task import N_OBS, OBS, obs_group
from ..physics.config import needs_extra, to_dict
from .controller_registry import (  # noqa: F401 (the registry's interface: import it from here)
    Controller, SpecOptions, baselines, check_controller_spec, controller_names, controller_of, controllers_help,
    display_name, get_controller, is_controller, make_controller, parse_controller_spec, policy_usage,
    register_controller, residual_bases, spec_forms, suite_baselines, unregister_controller,
)
from .controller_settings import (
    GATE_WAIT_STEPS, PATH_KEYS, SLIPFEEDBACK_KEYS, FixedForceSettings, SlipFeedbackSettings,
)
from .friction import N_FEATURES, FrictionEstimator, closing_features, with_estimator
from .result_cache import cached_float

# observation entries read (envs.task.OBS_NAMES); a stacked history ends with the current frame
_NORMAL = obs_group("normal_force")
_SLIP = obs_group("slip_speed")
_TRAVEL = OBS["pull_distance"]
_CONTACT = obs_group("contact_fraction")
_LIFT_SLIP = OBS["lift_slip"]


def _current_frame(obs: np.ndarray, config: GraspLiftConfig) -> np.ndarray:
    obs = np.atleast_2d(obs)
    frame = obs.shape[1] // config.obs_history
    return obs[:, frame * (config.obs_history - 1) : frame * config.obs_history]


class Policy(Protocol):
    name: str

    def reset(self, infos: Sequence[dict[str, Any]]) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


class FixedForcePolicy:
    """Close at full speed until the pinch force reaches ``force_N``, then pull while regulating it."""

    def __init__(self, config: GraspLiftConfig | None = None, force_N: float = 2.5, pull: float = 0.5,
                 gain: float = 2.0, name: str | None = None) -> None:
        FixedForceSettings(force_N, pull)  # (ValueError naming a bad one)
        self.config = config or GraspLiftConfig()
        self.force_N = float(force_N)
        self.force = np.array([self.force_N])
        self.pull = pull
        self.gain = gain
        self.name = name or f"fixed{force_N:g}N"
        self._grasped = np.zeros(1, dtype=bool)

    def setpoint(self, info: dict[str, Any]) -> float:
        """Pinch-force set-point (N) at the start of an episode with reset info ``info``."""
        return self.force_N

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        self._grasped = np.zeros(len(infos), dtype=bool)
        self.force = np.array([self.setpoint(info) for info in infos], dtype=np.float64)

    def reset_one(self, index: int, info: dict[str, Any]) -> None:
        """Start a new episode in batch slot ``index`` only (the others keep their state)."""
        self._grasped[index] = False
        self.force[index] = self.setpoint(info)

    def _pinch(self, obs: np.ndarray) -> np.ndarray:
        return obs[:, _NORMAL].sum(axis=1) * self.config.reference_force_N

    def act(self, obs: np.ndarray) -> np.ndarray:
        cfg = self.config
        obs = _current_frame(obs, cfg)
        pinch = self._pinch(obs)
        # grasped once the pinch force is (nearly) at the set-point: a force loop approaches it asymptotically
        self._grasped |= pinch >= (0.95 if cfg.jaw_action == "force" else 1.0) * self.force
        if cfg.jaw_action == "force":
            jaw = pinch_action(self.force, cfg)
        else:  # regulate the force through the closing speed (P control at the agent rate)
            jaw = np.where(self._grasped, np.clip(self.gain * (self.force - pinch) / self.force, -1.0, 1.0), 1.0)
        if cfg.pull_action == "travel":  # a travel set-point that advances at the pull speed once grasped
            travel = obs[:, _TRAVEL] * cfg.lift_target_m
            step = self.pull * max_pull_speed(cfg) * cfg.agent_dt_s
            target = np.where(self._grasped, np.minimum(travel + step, cfg.max_travel_m), 0.0)
            pull = 2.0 * target / cfg.max_travel_m - 1.0
        elif cfg.pull_action == "forward_speed":
            pull = np.where(self._grasped, pull_action(self.pull, cfg), -1.0)
        else:
            pull = np.where(self._grasped, self.pull, 0.0)
        return np.stack([np.broadcast_to(jaw, pull.shape), pull], axis=1).astype(np.float32)


class SlipReactivePolicy(FixedForcePolicy):
    """Start with a light grip; raise the force set-point by ``step_N`` whenever slip is sensed."""

    def __init__(self, config: GraspLiftConfig | None = None, initial_force_N: float = 1.2, step_N: float = 0.3,
                 max_force_N: float = 4.0, slip_threshold: float = 0.05, pull: float = 0.5) -> None:
        super().__init__(config, initial_force_N, pull, name="reactive")
        self.initial = initial_force_N
        self.step = step_N
        self.max_force = max_force_N
        self.slip_threshold = slip_threshold

    def setpoint(self, info: dict[str, Any]) -> float:
        return self.initial

    def act(self, obs: np.ndarray) -> np.ndarray:
        frame = _current_frame(obs, self.config)
        slipping = self._grasped & (frame[:, _SLIP].max(axis=1) > self.slip_threshold)
        self.force = np.where(slipping, np.minimum(self.force + self.step, self.max_force), self.force)
        return super().act(obs)


class SlipFeedbackPolicy:
    """Grip lightly, pull, and hold the pinch set-point at ``initial_force_N + gain_N_per_mm x`` (slip since lifting
    began, mm), never lowering it: the grip grows with the load only as far as the tissue shows it must.

    It reads the contact fractions (to know when the jaws hold: ``contact_jaws`` jaws touching for
    ``settle_steps`` steps, then the pull starts) and the slip since lifting began (``lift_slip``), never a force
    reading, so force-sensor noise and bias leave its actions unchanged. Needs a force-set-point jaw and a
    forward-speed pull (the benchmark task's interface).

    Two options change that. ``pinch_gate`` > 0: the pull also waits until the pinch reading reaches that fraction
    of the set-point (at most ``GATE_WAIT_STEPS`` steps longer), so the grip is there before the tissue is loaded;
    the controller then reads the force sensors. ``oracle_margin`` > 0: each episode's initial grip is that multiple
    of the oracle's minimal fixed force at the episode's friction and this pull speed (:func:`minimal_force`, told
    mu by the reset info as :class:`OraclePolicy` is): a reference for what knowing the friction is worth, not a
    controller a grasper could run. ``friction_estimator`` (a :class:`.friction.FrictionEstimator`, with a pinch
    gate): the jaws close to the estimator's probe grip; when the gate opens, the friction is estimated from the frames
    seen while closing, the set-point rises to ``estimate_margin`` x the minimal fixed force at the estimate, and the
    pull waits for the pinch to reach the gate's share of that (``mu_estimate`` holds each episode's estimate).
    """

    def __init__(self, config: GraspLiftConfig | None = None, settings: SlipFeedbackSettings | None = None,
                 friction_estimator: FrictionEstimator | None = None, **fields: Any) -> None:
        """``settings``: the controller's parameter record (default :class:`SlipFeedbackSettings`), with any of its
        ``fields`` given by keyword replaced (``SlipFeedbackPolicy(task, gain_N_per_mm=0.5)``)."""
        self.config = config or GraspLiftConfig()
        if not setpoint_interface(self.config):
            raise ValueError("the slip-feedback controller needs jaw_action: force and pull_action: forward_speed, "
                             f"got {self.config.jaw_action!r} / {self.config.pull_action!r}")
        if "told_mu" in fields:  # (a flag where it is given by keyword; a 0/1 number in the record)
            fields["told_mu"] = float(fields["told_mu"])
        st = dataclasses.replace(settings or SlipFeedbackSettings(), **fields)
        if st.told_mu and friction_estimator is None:
            raise ValueError("told_mu needs a friction_estimator (its probe grip and force table; the told mu replaces "
                             "its estimate)")
        if friction_estimator is not None:
            if not st.pinch_gate or st.oracle_margin:
                raise ValueError("friction_estimator needs pinch_gate > 0 (the estimate is made when the gate opens) "
                                 "and oracle_margin 0 (told mu, nothing is estimated)")
            if not math.isclose(st.initial_force_N, friction_estimator.probe_force_N):
                raise ValueError(f"initial_force_N must be the friction estimator's probe grip, "
                                 f"{friction_estimator.probe_force_N} N, got {st.initial_force_N!r}")
        self.settings = st
        self.initial = float(st.initial_force_N)
        self.gain = float(st.gain_N_per_mm)
        self.max_force = float(st.max_force_N)
        self.pull = float(st.pull)
        self.contact_jaws = int(st.contact_jaws)
        self.settle_steps = int(st.settle_steps)
        self.pinch_gate = float(st.pinch_gate)
        self.oracle_margin = float(st.oracle_margin)
        self.estimate_margin = float(st.estimate_margin)
        self.estimator = friction_estimator
        self.told_mu = bool(st.told_mu)
        self.name = "slipfeedback"
        self._size(1)

    def _size(self, n: int) -> None:
        self.start = np.full(n, self.initial)  # each episode's initial grip, N
        self.force = self.start.copy()
        self._held = np.zeros(n, dtype=np.int64)  # steps since the jaws first held
        self._pulling = np.zeros(n, dtype=bool)
        self.mu_estimate = np.full(n, np.nan)  # with a friction estimator: each episode's estimate
        self.closing_features = np.full((n, N_FEATURES), np.nan)  # and the closing features it was made from
        self._told = np.full(n, np.nan)  # with told_mu: each episode's mu, from its reset info
        self._frames: list[list[np.ndarray]] = [[] for _ in range(n)]  # the frames seen while closing
        self._regrip = np.full(n, -1, dtype=np.int64)  # steps since the estimate raised the grip (-1: not yet)

    @property
    def pulling(self) -> np.ndarray:
        """Per episode, whether the pull has started (after the contact rule, the gate and any regrip)."""
        return self._pulling.copy()

    def initial_force(self, info: dict[str, Any]) -> float:
        """The initial grip (N) of an episode with reset info ``info``."""
        if not self.oracle_margin:
            return self.initial
        if "mu" not in info:
            raise ValueError("the slip-feedback controller with oracle_margin needs the episode's mu in the reset info")
        force = minimal_force(self.config, round(float(info["mu"]), 3), self.pull, ORACLE_TOLERANCE_N)
        return min(self.oracle_margin * force, self.max_force)

    def _told_mu(self, info: dict[str, Any]) -> float:
        if not self.told_mu:
            return math.nan
        if "mu" not in info:
            raise ValueError("the slip-feedback controller with told_mu needs the episode's mu in the reset info")
        return float(info["mu"])

    def _closing_grip(self, info: dict[str, Any]) -> float:
        """The grip an episode closes to: told mu, the probe grip or less where the friction needs less (it need not
        probe further than the grip it will set); else the initial grip."""
        start = self.initial_force(info)
        if self.told_mu:
            start = min(start, self.estimate_margin * self.estimator.grip_N(self._told_mu(info)))
        return start

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        self._size(len(infos))
        self.start[:] = [self._closing_grip(info) for info in infos]
        self.force[:] = self.start
        self._told[:] = [self._told_mu(info) for info in infos]

    def reset_one(self, index: int, info: dict[str, Any]) -> None:
        """Start a new episode in batch slot ``index`` only (the others keep their state)."""
        self.start[index] = self.force[index] = self._closing_grip(info)
        self._held[index] = 0
        self._pulling[index] = False
        self.mu_estimate[index] = np.nan
        self.closing_features[index] = np.nan
        self._frames[index] = []
        self._regrip[index] = -1
        self._told[index] = self._told_mu(info)

    def act(self, obs: np.ndarray) -> np.ndarray:
        cfg = self.config
        frame = _current_frame(obs, cfg)
        touching = (frame[:, _CONTACT] > 0.0).sum(axis=1) >= self.contact_jaws
        self._held += (touching | (self._held > 0)).astype(np.int64)
        ready = self._held > self.settle_steps
        if self.pinch_gate:
            pinch = frame[:, _NORMAL].sum(axis=1) * cfg.reference_force_N
            ready &= (pinch >= self.pinch_gate * self.force) | (self._held > self.settle_steps + GATE_WAIT_STEPS)
        if self.estimator is not None:
            ready = self._estimate(frame, ready, pinch)
        self._pulling |= ready
        slip_mm = frame[:, _LIFT_SLIP] * cfg.lift_slip_tolerance_m * 1e3
        self.force = np.maximum(self.force, np.minimum(self.start + self.gain * slip_mm, self.max_force))
        pull = np.where(self._pulling, pull_action(self.pull, cfg), -1.0)
        return np.stack([pinch_action(self.force, cfg), pull], axis=1).astype(np.float32)

    def _estimate(self, frame: np.ndarray, gate_open: np.ndarray, pinch: np.ndarray) -> np.ndarray:
        """Record the closing, estimate the friction where the gate first opens and raise the grip from it; the
        episodes whose pull may start: the raised grip reached (the gate's share of it, or GATE_WAIT_STEPS)."""
        closing = np.isnan(self.mu_estimate)
        for b in np.flatnonzero(closing):  # (the task's entries; privileged ones follow them)
            self._frames[b].append(np.array(frame[b, :N_OBS], dtype=np.float64))
        for b in np.flatnonzero(closing & gate_open):
            self.closing_features[b] = closing_features(np.array(self._frames[b]))
            mu = self._told[b] if self.told_mu else self.estimator.mu(self.closing_features[b])
            self.mu_estimate[b] = mu
            self.start[b] = max(self.start[b], min(self.estimate_margin * self.estimator.grip_N(mu), self.max_force))
            self.force[b] = max(self.force[b], self.start[b])
            self._regrip[b] = 0
            self._frames[b] = []
        regrip = self._regrip >= 0
        self._regrip[regrip] += 1
        return regrip & ((pinch >= self.pinch_gate * self.force) | (self._regrip > GATE_WAIT_STEPS))


class OraclePolicy(FixedForcePolicy):
    """Knows mu (from the reset info): the minimal slip-free fixed force at that mu, times (1 + margin)."""

    def __init__(self, config: GraspLiftConfig | None = None, margin: float = 0.1, pull: float = 0.5,
                 tolerance_N: float = 0.1) -> None:
        super().__init__(config, 1.0, pull, name="oracle")
        self.margin = margin
        self.tolerance = tolerance_N

    def setpoint(self, info: dict[str, Any]) -> float:
        return (1.0 + self.margin) * minimal_force(self.config, round(float(info["mu"]), 3), self.pull, self.tolerance)


#: the tolerance of the minimal force a slip-feedback controller told mu starts from, N
ORACLE_TOLERANCE_N = 0.02


@functools.lru_cache(maxsize=8)
def max_pull_speed(config: GraspLiftConfig) -> float:
    """The arm's top pull speed on the task ``config``, m/s (its own, else its grasper file's)."""
    if config.max_pull_speed_m_s is not None:
        return config.max_pull_speed_m_s
    from ..physics.config import builtin_config
    from ..physics.grasper import GrasperParams
    from ..physics.scenario import load_params

    path = config.grasper_config or builtin_config("grasper/env.yaml")
    return load_params(path, "grasper", GrasperParams).max_pull_speed_m_s


@functools.lru_cache(maxsize=256)
def _minimal_force_cached(config: GraspLiftConfig, mu: float, pull: float, tolerance: float) -> float:
    """:func:`_minimal_force_search`, kept for the process and, across processes, on disk (:mod:`.result_cache`:
    keyed on the config, the package's files and the numerical stack; a config naming its own tissue or grasper
    file is searched every time, as the key cannot see that file's edits)."""
    key = {"config": to_dict(config), "mu": mu, "pull": pull, "tolerance_N": tolerance}
    own_files = config.tissue_config is not None or config.grasper_config is not None
    return cached_float("oracle_minimal_force", key, lambda: _minimal_force_search(config, mu, pull, tolerance),
                        cacheable=not own_files)


def _minimal_force_search(config: GraspLiftConfig, mu: float, pull: float, tolerance: float) -> float:
    """The bisection behind :func:`minimal_force`."""
    from ..envs.grasp_lift import GraspLiftVectorEnv

    lo, hi = 0.2, 2.0 * config.reference_force_N
    candidates = np.linspace(lo, hi, 8)
    # one batched sweep brackets the answer, then bisection refines it (each probe: nominal tissue, no
    # pose jitter, so the answer is the physics of this mu, not of a lucky draw)
    env = GraspLiftVectorEnv(len(candidates), config)
    ok = _probe(env, candidates, mu, pull)
    if not ok.any():
        return float(hi)
    first = int(np.argmax(ok))
    lo = candidates[first - 1] if first > 0 else lo
    hi = candidates[first]
    env1 = GraspLiftVectorEnv(4, config)
    while hi - lo > tolerance:
        mids = np.linspace(lo, hi, 6)[1:-1]
        res = _probe(env1, mids, mu, pull)
        if res.any():
            k = int(np.argmax(res))
            hi = mids[k]
            lo = mids[k - 1] if k > 0 else lo
        else:
            lo = mids[-1]
    return float(hi)


def _probe(env, forces: np.ndarray, mu: float, pull: float) -> np.ndarray:
    """Success of the fixed-force controller at each force (one batched episode each)."""
    opts = {"mu": mu, "stiffness_scale": 1.0, "mass_scale": 1.0, "pose_offset_m": 0.0, "pose_tilt_deg": 0.0,
            "pose_azimuth_deg": 0.0}
    return _fixed_force_success(env, forces, pull, seed=0, options=opts)


def _fixed_force_success(env, forces: np.ndarray, pull: float, **reset) -> np.ndarray:
    """Whether the fixed-force controller lifts and holds each of ``env``'s episodes (``env.reset(**reset)``), env
    k at ``forces[k]``."""
    obs, info = env.reset(**reset)
    pol = FixedForcePolicy(env.config, 1.0, pull)
    pol.reset([{}] * env.num_envs)
    pol.force = np.asarray(forces, dtype=np.float64)
    done = np.zeros(env.num_envs, dtype=bool)
    success = np.zeros(env.num_envs, dtype=bool)
    core = env.core
    for _ in range(env.config.max_episode_steps):
        act = pol.act(obs)
        # (ended episodes' tissues stand still, as in the evaluation)
        obs, _, term, trunc, info = core.step(act, advance=np.flatnonzero(~done))
        success |= (~done) & info["is_success"]
        done |= term | trunc
        if done.all():
            break
    return success


#: the forces a hindsight search tries first, N (then it bisects between the two that bracket an episode's minimum)
HINDSIGHT_GRID_N = (0.4, 0.6, 0.8, 1.0, 1.25, 1.6, 2.0, 3.0, 5.0)


def episode_minimal_forces(config: GraspLiftConfig, mus: Sequence[float], seeds: Sequence[int],
                           options: dict[str, float] | None = None, pull: float = 0.5,
                           tolerance_N: float = 0.05) -> np.ndarray:
    """The hindsight oracle: for each episode (friction ``mus[k]``, reset seed ``seeds[k]``, reset ``options``: the
    episode a policy meets in an evaluation with those seeds), the smallest fixed pinch force (N, within
    ``tolerance_N``) with which the fixed-force controller at pull ``pull`` lifts and holds it; NaN where no force
    in HINDSIGHT_GRID_N does. Unlike :func:`minimal_force` (the nominal tissue), it sees each episode's own draws:
    placement error, stiffness and mass, sensing and actuation perturbations."""
    from ..envs.grasp_lift import GraspLiftVectorEnv

    if len(mus) != len(seeds):
        raise ValueError(f"mus and seeds must have one entry per episode, got {len(mus)} and {len(seeds)}")
    grid = np.asarray(HINDSIGHT_GRID_N)
    n, g = len(seeds), len(grid)

    def probe(forces: np.ndarray, episodes: np.ndarray) -> np.ndarray:
        env = GraspLiftVectorEnv(len(forces), config)
        opts = {**(options or {}), "mu": [float(mus[k]) for k in episodes]}
        return _fixed_force_success(env, forces, pull, seed=[int(seeds[k]) for k in episodes], options=opts)

    held = probe(np.tile(grid, n), np.repeat(np.arange(n), g)).reshape(n, g)
    lo, hi = np.zeros(n), np.full(n, np.nan)
    for k in range(n):
        if held[k].any():
            j = int(np.argmax(held[k]))
            hi[k], lo[k] = grid[j], (grid[j - 1] if j > 0 else 0.5 * grid[0])
    while True:  # every open bracket split in four per round, all episodes in one batch
        live = np.flatnonzero(np.isfinite(hi) & (hi - lo > tolerance_N))
        if not len(live):
            return hi
        mids = np.stack([np.linspace(lo[k], hi[k], 5)[1:-1] for k in live])
        res = probe(mids.ravel(), np.repeat(live, 3)).reshape(len(live), 3)
        for q, k in enumerate(live):
            if res[q].any():
                j = int(np.argmax(res[q]))
                hi[k], lo[k] = mids[q, j], (mids[q, j - 1] if j > 0 else lo[k])
            else:
                lo[k] = mids[q, -1]


def minimal_force(config: GraspLiftConfig, mu: float, pull: float = 0.5, tolerance_N: float = 0.1) -> float:
    """Smallest fixed pinch force (N) that lifts the nominal tissue without slip at friction ``mu``."""
    return _minimal_force_cached(config, float(mu), float(pull), float(tolerance_N))


class TorchScriptPolicy:
    """A policy exported by the torch-native PPO (:func:`.torch_ppo.train_torch`): ``policy.pt``, TorchScript of
    the actor (deterministic, observation normaliser inside), with ``policy.json`` beside it (the actor's
    observation columns and the training config)."""

    def __init__(self, path: str | Path, name: str | None = None) -> None:
        with needs_extra("train", "a TorchScript policy"):
            import torch

        from .learners.rsl_layout import read_meta

        path = Path(path)
        meta = read_meta(path)  # (ConfigError where the description beside it is missing or broken)
        self.module = torch.jit.load(str(path), map_location="cpu")
        self.columns = np.asarray(meta["actor_columns"], dtype=np.int64)
        self.name = name or meta.get("name", path.stem)

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        import torch

        x = torch.as_tensor(np.atleast_2d(obs)[:, self.columns], dtype=torch.float32)
        with torch.no_grad():
            return self.module(x).numpy().astype(np.float32)


class ConstantPolicy:
    """The same action every step: ``zero`` (action 0: in the default force/travel mode a 2.5 N set-point
    and a 30 mm travel set-point from the first step) or ``idle`` (never touch: no force, no pull)."""

    def __init__(self, action: Sequence[float], name: str) -> None:
        self.action = np.asarray(action, dtype=np.float32)
        self.name = name

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.tile(self.action, (np.atleast_2d(obs).shape[0], 1))


def idle_action(config: GraspLiftConfig) -> np.ndarray:
    """The action that leaves the tissue alone: jaws at zero force (or still), no pull."""
    return np.array([-1.0 if config.jaw_action == "force" else 0.0, 0.0 if config.pull_action == "speed" else -1.0])


def make_policy(spec: str, config: GraspLiftConfig | None = None) -> Policy:
    """The policy of a spec: a registered controller (``fixed``, ``fixed:<N>``, ``slipfeedback:key=value,...``,
    :func:`controller_names`) or a path to a saved model of any learner (run by the learner recorded beside it)."""
    config = config or GraspLiftConfig()
    if is_controller(spec):
        return make_controller(spec, config)
    from .learners.base import learner_of_model

    return learner_of_model(spec).load_policy(Path(spec))


# ------------------------------------------------------------------------------------------------
# the built-in controllers (adding one: its class above and one entry here; docs/learners.md)
# ------------------------------------------------------------------------------------------------


def _fixed_display(name: str) -> str | None:
    """'fixed2.5N' (a fixed-force policy's name) -> 'fixed 2.5 N'."""
    return f"fixed {name[5:-1]} N" if name.startswith("fixed") and name.endswith("N") else None


def _zero(config: GraspLiftConfig) -> ConstantPolicy:
    return ConstantPolicy([0.0, 0.0], "zero")


def _idle(config: GraspLiftConfig) -> ConstantPolicy:
    return ConstantPolicy(idle_action(config), "idle")


register_controller(
    "fixed", FixedForcePolicy, settings=FixedForceSettings, display=_fixed_display,
    options=SpecOptions(positional="force_N", usage="<N>"), suite_baseline=True, residual_base=True,
    help="close to a fixed pinch force (default 2.5 N; fixed:<N> sets it), then pull holding it")
register_controller(
    "reactive", SlipReactivePolicy, display="slip-reactive", baseline=True, residual_base=True,
    help="slip-reactive: a light grip, raised a step whenever the jaws sense slip")
register_controller(
    "slipfeedback", SlipFeedbackPolicy, settings=SlipFeedbackSettings, display="slip-feedback",
    options=SpecOptions(keys=SLIPFEEDBACK_KEYS, path_keys=PATH_KEYS,
                        usage="initial=N,gain=N,pull=F,max=N,gate=F,oracle=X,estimator=FILE|builtin,margin=X,told=0|1"),
    resolve=with_estimator, suite_baseline=True, residual_base=True, needs_setpoint_interface=True,
    reports_pull=True,
    help="slip-feedback: a light grip raised in proportion to the slip since lifting began (reads no force)")
register_controller(
    "oracle", OraclePolicy, display="oracle (min. force + 10%)", baseline=True,
    help="told mu: the smallest fixed force that lifts without slip at it, plus 10 %")
register_controller("zero", _zero, help="action 0 every step")
register_controller("idle", _idle, help="never touches the tissue: no force, no pull")
