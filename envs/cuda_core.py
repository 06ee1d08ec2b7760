"""The GraspLift task on a CUDA GPU: the whole agent step (commands, physics, readouts, observation, reward,
termination and autoreset with domain randomisation) on the device, for thousands of tissues at once.

:class:`CudaGraspLiftCore` is :class:`.core.GraspLiftCore`'s task on :class:`~msdgrasp.physics.cuda_step.CudaBatch`.
One agent step is four kernel launches and no transfer:

====================  =====================================  ====================================================
kernel                threads                                what it does
====================  =====================================  ====================================================
``_command_kernel``   one per env                            actions -> pinch set-point / closing speed, pull speed
``_simulate_kernel``  one block per tissue (physics)         ``physics_steps_per_action`` x 1 ms of physics
``_task_kernel``      one block per env                      finiteness and smallest tet volume (block-parallel);
                                                             lift, slip, hold, reward terms, flags, observation
                                                             (thread 0: a few hundred flops per env)
``_reset_kernel``     one block per env that is done         settled state back (block-parallel), new friction,
                                                             scales and pose drawn on the device, first frame
====================  =====================================  ====================================================

Observations, rewards and flags stay in device arrays (:meth:`CudaGraspLiftCore.arrays`); a torch learner
reads them without a copy (:func:`as_torch`: ``__cuda_array_interface__``). The arithmetic is the CPU
task's (``core.py``), written per env: the tests compare both step by step in numba's CUDA simulator.

Differences from the CPU core, by design: the random numbers (xoroshiro128+ streams on the device, one per
env, seeded by ``seed``, instead of NumPy's per-env generators), so a GPU batch is reproducible by its own
seed but does not replay the CPU's episodes; a done env is reset in the same step (the observation returned
for it is its new episode's first; the last one of the old episode is in ``terminal_obs``, and
``truncated`` says which ends were time limits, for bootstrapping); ``reset(options)`` pins friction and
scales (``mu``, ``stiffness_scale``, ``mass_scale``) for every later episode until the next ``reset``.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, NamedTuple

import numpy as np
from numba import cuda
from numba.cuda.random import create_xoroshiro128p_states, xoroshiro128p_normal_float64, xoroshiro128p_uniform_float64

from ..physics.config import ConfigError, check_choice, check_range
from ..physics.contact import (
    G_GAIN, G_PINCH, G_SETPOINT, G_VMAX, J_CONTACT, J_NORMAL, J_PEAK_PRESSURE, J_SLIP, J_SLIP_DIST, J_TX, J_TY, J_TZ,
)
from ..physics.cuda_step import PRECISIONS, THREADS_PER_BLOCK, CudaBatch, _tet_edges, to_device
from ..physics.viscoelastic import elongations
from .core import OBS_NAMES, GraspLiftConfig, GraspLiftCore

JAW_FORCE, JAW_SPEED = 0, 1
PULL_TRAVEL, PULL_SPEED, PULL_FORWARD = 0, 1, 2
#: the reward terms in ``terms`` (B, 9), in the CPU core's order (its info["reward_terms"] keys)
REWARD_TERMS = ("progress", "hold", "grasp", "slip", "force", "peak_force", "damage", "success", "failure")
#: the raw random draws of each episode, columns of ``draws`` (B, 12)
DRAW_COLUMNS = ("mu", "stiffness_scale", "mass_scale", "offset_dir_x", "offset_dir_y", "offset_dir_z", "offset_r",
                "tilt_axis_x", "tilt_axis_y", "tilt_axis_z", "tilt", "azimuth")
#: what ``reset(options=...)`` may pin (for every later episode)
GPU_PINNABLE = ("mu", "stiffness_scale", "mass_scale")
N_OBS = len(OBS_NAMES)


class TaskParams(NamedTuple):
    """The task's constants on the device (config values, SI units; choices as small integers)."""

    region: np.ndarray  # (R,) int: surface nodes the jaws may hold (their mean is the lift)
    nominal: np.ndarray  # (3,) nominal contact nodes per jaw
    x_start: np.ndarray  # (N,3) m settled positions
    fv_start: np.ndarray  # (E,) N settled Maxwell forces
    dl_start: np.ndarray  # (E,) m settled spring elongations
    pose_tip: np.ndarray  # (3,) m nominal grasp pose
    pose_axis: np.ndarray  # (3,)
    pose_e1: np.ndarray  # (3,)
    pull_dir: np.ndarray  # (3,)
    priv_nodes: np.ndarray  # (P,) int nodes of the privileged displacement observation
    start_radius: float  # m
    max_close: float  # m/s
    max_pull: float  # m/s
    agent_dt: float  # s
    jaw_mode: int
    pull_mode: int
    max_force: float  # N
    pinch_exp: float
    loop_gain: float  # m/s/N
    max_travel: float  # m
    obs_history: int
    frame_dim: int
    privileged: bool
    lift_target: float  # m
    hold_time: float  # s
    hold_slip_tol: float  # m
    lift_slip_tol: float  # m
    time_limit: float  # s
    max_steps: int
    ref_force: float  # N
    damage_stress: float  # Pa
    terminate_on_damage: bool
    lift_started_m: float
    inverted_is_failure: bool
    w_progress: float
    w_hold: float
    w_grasp: float
    grasp_force: float  # N
    w_slip_mm: float
    w_force: float
    w_peak: float
    peak_as_made: bool
    peak_mu_ref: float  # 0: the same charge at every mu
    w_damage: float
    w_success: float
    w_failure: float
    mu_lo: float
    mu_hi: float
    mu_log: bool
    ks_lo: float
    ks_hi: float
    ms_lo: float
    ms_hi: float
    pose_offset: float  # m
    pose_tilt: float  # rad
    pose_azimuth: float  # rad
    noise_std: float  # N


class TaskState(NamedTuple):
    """Per-env episode state and the step's outputs, batch first (device arrays)."""

    mu: np.ndarray  # (B,)
    tip0: np.ndarray  # (B,3) m grasper tip at the episode start
    region0: np.ndarray  # (B,3) m grasp region's mean at the episode start
    steps: np.ndarray  # (B,) int agent steps in the episode
    act: np.ndarray  # (B,2) this step's clipped action
    prev_action: np.ndarray  # (B,2)
    lift: np.ndarray  # (B,) m
    best_lift: np.ndarray  # (B,) m
    grip: np.ndarray  # (B,)
    slip_total: np.ndarray  # (B,) m
    lift_slip: np.ndarray  # (B,) m
    hold_time: np.ndarray  # (B,) s
    hold_slip: np.ndarray  # (B,) m
    peak_pinch: np.ndarray  # (B,) N
    peak_stress: np.ndarray  # (B,) Pa
    lift_started: np.ndarray  # (B,) bool
    hold_progress: np.ndarray  # (B,)
    travel_target: np.ndarray  # (B,) m
    frames: np.ndarray  # (B,H,F) observation history, oldest first
    obs: np.ndarray  # (B,H*F) float32: the observation (a new episode's first where done)
    terminal_obs: np.ndarray  # (B,H*F) float32: the last observation of an episode that ended this step
    reward: np.ndarray  # (B,)
    terms: np.ndarray  # (B,9) reward terms (REWARD_TERMS)
    terminated: np.ndarray  # (B,) bool
    truncated: np.ndarray  # (B,) bool
    done: np.ndarray  # (B,) bool: terminated | truncated (the reset kernel's mask)
    pinch: np.ndarray  # (B,) N pinch force of the last 1 ms
    stress: np.ndarray  # (B,) Pa peak contact pressure of the step
    contact: np.ndarray  # (B,) contact nodes
    is_success: np.ndarray  # (B,) bool
    lost_grasp: np.ndarray  # (B,) bool
    slipped: np.ndarray  # (B,) bool
    damaged: np.ndarray  # (B,) bool
    numerical_failure: np.ndarray  # (B,) bool
    min_volume_ratio: np.ndarray  # (B,)
    episode_return: np.ndarray  # (B,) sum of the rewards so far (of the episode that ended, where done)
    episode_length: np.ndarray  # (B,) int steps of the episode that ended (where done)
    episode_peak_pinch: np.ndarray  # (B,) N peak pinch of the episode that ended (where done)
    episode_slip: np.ndarray  # (B,) m slip of the episode that ended (where done)
    draws: np.ndarray  # (B,12) this episode's raw random draws (DRAW_COLUMNS)
    pin: np.ndarray  # (B,3) pinned mu, stiffness and mass scale (NaN: drawn)


# ------------------------------------------------------------------------------------------------
# device functions (per env; the CPU core's arithmetic, term for term)
# ------------------------------------------------------------------------------------------------


@cuda.jit(device=True)
def _travel(p, ts, s, b):
    """Grasper pull distance along the pull direction since the episode start, m."""
    return ((s.g_tip[b, 0] - ts.tip0[b, 0]) * p.pull_dir[0] + (s.g_tip[b, 1] - ts.tip0[b, 1]) * p.pull_dir[1]
            + (s.g_tip[b, 2] - ts.tip0[b, 2]) * p.pull_dir[2])


@cuda.jit(device=True)
def _region_mean(p, s, b, c):
    """Mean coordinate c of the grasp region's nodes (in node order, as NumPy's mean sums them)."""
    acc = 0.0
    for q in range(p.region.shape[0]):
        acc += s.x[b, p.region[q], c]
    return acc / p.region.shape[0]


@cuda.jit(device=True)
def _observe(p, s, out, ts, b, n0, n1, n2, fresh):
    """Write env b's current frame into the history (all of it when ``fresh``) and the observation."""
    h = p.obs_history
    fd = p.frame_dim
    if not fresh:  # drop the oldest frame
        for k in range(h - 1):
            for c in range(fd):
                ts.frames[b, k, c] = ts.frames[b, k + 1, c]
    o = ts.frames[b, h - 1]
    ref = p.ref_force
    tgt = p.lift_target
    rmin = s.g_rmin[b]
    o[0] = (s.g_radius[b] - rmin) / (p.start_radius - rmin)
    o[1] = -s.g_vradius[b] / p.max_close
    travel = _travel(p, ts, s, b)
    o[2] = travel / tgt
    o[3] = (s.g_vpull[b, 0] * p.pull_dir[0] + s.g_vpull[b, 1] * p.pull_dir[1] + s.g_vpull[b, 2] * p.pull_dir[2]) / p.max_pull
    for k in range(3):
        noise = n0 if k == 0 else (n1 if k == 1 else n2)
        jo = out.jaw_out[b, k]
        o[4 + k] = (jo[J_NORMAL] + noise) / ref
        tt = math.sqrt(jo[J_TX] * jo[J_TX] + jo[J_TY] * jo[J_TY] + jo[J_TZ] * jo[J_TZ])
        o[7 + k] = (tt + abs(noise)) / ref
        o[10 + k] = min(jo[J_CONTACT] / p.nominal[k], 2.0)
        o[13 + k] = jo[J_SLIP_DIST] / p.agent_dt / p.max_pull
        o[16 + k] = jo[J_SLIP] / max(jo[J_CONTACT], 1.0)
        o[28 + k] = o[7 + k] / max(o[4 + k], 0.05 / ref)
    o[19] = ts.prev_action[b, 0]
    o[20] = ts.prev_action[b, 1]
    o[21] = ts.steps[b] * p.agent_dt / p.time_limit
    o[22] = ts.lift[b] / tgt
    o[23] = ts.hold_progress[b]
    o[24] = ts.hold_slip[b] / p.hold_slip_tol if p.hold_slip_tol > 0 else 0.0
    o[25] = (travel - ts.lift[b]) / tgt
    o[26] = ts.peak_pinch[b] / ref
    o[27] = ts.best_lift[b] / tgt
    o[31] = ts.lift_slip[b] / p.lift_slip_tol
    if p.privileged:
        o[N_OBS] = ts.mu[b]
        o[N_OBS + 1] = s.kscale[b]
        o[N_OBS + 2] = s.mscale[b]
        for q in range(p.priv_nodes.shape[0]):
            i = p.priv_nodes[q]
            for c in range(3):
                o[N_OBS + 3 + 3 * q + c] = (s.x[b, i, c] - p.x_start[i, c]) / tgt
    if fresh:
        for k in range(h - 1):
            for c in range(fd):
                ts.frames[b, k, c] = o[c]
    for k in range(h):
        for c in range(fd):
            ts.obs[b, k * fd + c] = ts.frames[b, k, c]


@cuda.jit(device=True)
def _task_update(p, s, out, ts, rng, b, finite, vratio):
    """One agent step of env b after the physics: lift, slip, hold, reward terms, flags, observation."""
    dt = p.agent_dt
    ts.steps[b] += 1
    ok = finite and (vratio > 0.0 or not p.inverted_is_failure)  # an inverted tet's forces push the wrong way
    slip = (out.jaw_out[b, 0, J_SLIP_DIST] + out.jaw_out[b, 1, J_SLIP_DIST] + out.jaw_out[b, 2, J_SLIP_DIST]) / 3.0
    pinch = out.jaw_out[b, 0, J_NORMAL] + out.jaw_out[b, 1, J_NORMAL] + out.jaw_out[b, 2, J_NORMAL]
    stress = max(max(out.jaw_out[b, 0, J_PEAK_PRESSURE], out.jaw_out[b, 1, J_PEAK_PRESSURE]),
                 out.jaw_out[b, 2, J_PEAK_PRESSURE])
    contact = out.jaw_out[b, 0, J_CONTACT] + out.jaw_out[b, 1, J_CONTACT] + out.jaw_out[b, 2, J_CONTACT]
    lift_new = ((_region_mean(p, s, b, 0) - ts.region0[b, 0]) * p.pull_dir[0]
                + (_region_mean(p, s, b, 1) - ts.region0[b, 1]) * p.pull_dir[1]
                + (_region_mean(p, s, b, 2) - ts.region0[b, 2]) * p.pull_dir[2])
    tgt = p.lift_target
    best = max(ts.best_lift[b], min(lift_new, tgt))
    progress = (best - ts.best_lift[b]) / tgt
    ts.best_lift[b] = best
    ts.lift[b] = lift_new
    grip = min(pinch / p.grasp_force, 1.0)
    grip_gain = grip - ts.grip[b]
    ts.grip[b] = grip
    ts.slip_total[b] += slip
    peak_rise = max(pinch - ts.peak_pinch[b], 0.0)
    ts.peak_pinch[b] = max(ts.peak_pinch[b], pinch)
    ts.peak_stress[b] = max(ts.peak_stress[b], stress)
    if lift_new >= p.lift_started_m:
        ts.lift_started[b] = True
    if ts.lift_started[b]:
        ts.lift_slip[b] += slip
    slipped = ts.lift_slip[b] > p.lift_slip_tol
    at_target = lift_new >= tgt
    if at_target:
        ts.hold_time[b] += dt
        ts.hold_slip[b] += slip
    else:
        ts.hold_time[b] = 0.0
        ts.hold_slip[b] = 0.0
    if ts.hold_slip[b] > p.hold_slip_tol:  # a hold spoilt by slip starts over
        ts.hold_time[b] = 0.0
        ts.hold_slip[b] = 0.0
    if p.hold_time > 0:
        hold_new = min(ts.hold_time[b] / p.hold_time, 1.0)
    else:
        hold_new = 1.0 if at_target else 0.0
    hold_gain = hold_new - ts.hold_progress[b]
    ts.hold_progress[b] = hold_new
    success = at_target and ts.hold_time[b] >= p.hold_time - 1e-9 and not slipped
    lost = ts.lift_started[b] and contact == 0
    damaged = stress > p.damage_stress
    failed = not ok
    terminated = success or lost or failed or (damaged and p.terminate_on_damage)
    truncated = (not terminated) and ts.steps[b] >= p.max_steps
    unsuccessful = (terminated or truncated) and not success
    if p.peak_as_made:  # charged as made, refunded without success
        peak_charge = peak_rise - (ts.peak_pinch[b] if unsuccessful else 0.0)
    else:
        peak_charge = ts.peak_pinch[b] if success else 0.0
    peak_charge = peak_charge * (ts.mu[b] / p.peak_mu_ref if p.peak_mu_ref > 0.0 else 1.0)
    t = ts.terms[b]
    t[0] = p.w_progress * progress
    t[1] = p.w_hold * hold_gain
    t[2] = p.w_grasp * grip_gain
    t[3] = -p.w_slip_mm * slip * 1e3
    t[4] = -p.w_force * (pinch / p.ref_force) * dt
    t[5] = -p.w_peak * peak_charge / p.ref_force
    t[6] = -p.w_damage * (1.0 if damaged else 0.0)
    t[7] = p.w_success * (1.0 if success else 0.0)
    t[8] = -p.w_failure * (1.0 if unsuccessful else 0.0)
    reward = 0.0
    for k in range(9):
        reward += t[k]
    if failed:  # a blown-up tissue: never hand out NaN observations or rewards
        reward = -p.w_failure
        for k in range(9):
            if not math.isfinite(t[k]):
                t[k] = 0.0
        ts.lift[b] = 0.0
        ts.grip[b] = 0.0
    ts.reward[b] = reward
    ts.prev_action[b, 0] = ts.act[b, 0]
    ts.prev_action[b, 1] = ts.act[b, 1]
    n0 = p.noise_std * xoroshiro128p_normal_float64(rng, b)
    n1 = p.noise_std * xoroshiro128p_normal_float64(rng, b)
    n2 = p.noise_std * xoroshiro128p_normal_float64(rng, b)
    _observe(p, s, out, ts, b, n0, n1, n2, False)
    if failed:
        for k in range(ts.frames.shape[1]):
            for c in range(ts.frames.shape[2]):
                ts.frames[b, k, c] = 0.0
        for c in range(ts.obs.shape[1]):
            ts.obs[b, c] = 0.0
    ts.pinch[b] = pinch
    ts.stress[b] = stress
    ts.contact[b] = contact
    ts.is_success[b] = success
    ts.lost_grasp[b] = lost
    ts.slipped[b] = slipped and not lost
    ts.damaged[b] = damaged
    ts.numerical_failure[b] = failed
    ts.min_volume_ratio[b] = vratio
    ts.terminated[b] = terminated
    ts.truncated[b] = truncated
    done = terminated or truncated
    ts.done[b] = done
    # (an episode's first step starts the sum: the same-step reset must leave an ended episode's return)
    ts.episode_return[b] = reward if ts.steps[b] == 1 else ts.episode_return[b] + reward
    if done:
        ts.episode_length[b] = ts.steps[b]
        ts.episode_peak_pinch[b] = ts.peak_pinch[b]
        ts.episode_slip[b] = ts.slip_total[b]
        for c in range(ts.obs.shape[1]):
            ts.terminal_obs[b, c] = ts.obs[b, c]


@cuda.jit(device=True)
def _rotate(v0, v1, v2, k0, k1, k2, ang):
    """Rodrigues rotation of v about the unit axis k (core._rotate)."""
    c = math.cos(ang)
    sn = math.sin(ang)
    kv = k0 * v0 + k1 * v1 + k2 * v2
    return (v0 * c + (k1 * v2 - k2 * v1) * sn + k0 * kv * (1 - c),
            v1 * c + (k2 * v0 - k0 * v2) * sn + k1 * kv * (1 - c),
            v2 * c + (k0 * v1 - k1 * v0) * sn + k2 * kv * (1 - c))


@cuda.jit(device=True)
def _draw_episode(p, s, ts, rng, b):
    """Draw env b's friction, scales and pose (core.reset's draws, in its order), pinned values aside."""
    d = ts.draws[b]
    u = xoroshiro128p_uniform_float64(rng, b)
    if p.mu_log:
        lo = math.log(p.mu_lo)
        d[0] = math.exp(lo + (math.log(p.mu_hi) - lo) * u)
    else:
        d[0] = p.mu_lo + (p.mu_hi - p.mu_lo) * u
    d[1] = p.ks_lo + (p.ks_hi - p.ks_lo) * xoroshiro128p_uniform_float64(rng, b)
    d[2] = p.ms_lo + (p.ms_hi - p.ms_lo) * xoroshiro128p_uniform_float64(rng, b)
    for c in range(3):
        d[3 + c] = xoroshiro128p_normal_float64(rng, b)
    d[6] = xoroshiro128p_uniform_float64(rng, b) ** (1.0 / 3.0)
    for c in range(3):
        d[7 + c] = xoroshiro128p_normal_float64(rng, b)
    d[10] = -1.0 + 2.0 * xoroshiro128p_uniform_float64(rng, b)
    d[11] = -1.0 + 2.0 * xoroshiro128p_uniform_float64(rng, b)
    mu = d[0] if math.isnan(ts.pin[b, 0]) else ts.pin[b, 0]
    ks = d[1] if math.isnan(ts.pin[b, 1]) else ts.pin[b, 1]
    ms = d[2] if math.isnan(ts.pin[b, 2]) else ts.pin[b, 2]
    ts.mu[b] = mu
    s.mu_s[b] = mu
    s.mu_k[b] = mu
    s.kscale[b] = ks
    s.mscale[b] = ms
    # the pose (core.perturbed_pose): tip offset normal to the axis, axis tilt, jaw azimuth
    a0, a1, a2 = p.pose_axis[0], p.pose_axis[1], p.pose_axis[2]
    da = d[3] * a0 + d[4] * a1 + d[5] * a2
    e0, e1, e2 = d[3] - a0 * da, d[4] - a1 * da, d[5] - a2 * da
    nrm = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) + 1e-12
    r = p.pose_offset * d[6]
    s.g_tip[b, 0] = p.pose_tip[0] + r * (e0 / nrm)
    s.g_tip[b, 1] = p.pose_tip[1] + r * (e1 / nrm)
    s.g_tip[b, 2] = p.pose_tip[2] + r * (e2 / nrm)
    t0, t1, t2 = a1 * d[9] - a2 * d[8], a2 * d[7] - a0 * d[9], a0 * d[8] - a1 * d[7]
    nrm = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2) + 1e-12
    t0, t1, t2 = t0 / nrm, t1 / nrm, t2 / nrm
    ang = p.pose_tilt * d[10]
    x0, x1, x2 = _rotate(a0, a1, a2, t0, t1, t2, ang)
    f0, f1, f2 = _rotate(p.pose_e1[0], p.pose_e1[1], p.pose_e1[2], t0, t1, t2, ang)
    f0, f1, f2 = _rotate(f0, f1, f2, x0, x1, x2, p.pose_azimuth * d[11])
    s.g_axis[b, 0] = x0
    s.g_axis[b, 1] = x1
    s.g_axis[b, 2] = x2
    s.g_e1[b, 0] = f0
    s.g_e1[b, 1] = f1
    s.g_e1[b, 2] = f2
    for c in range(3):
        ts.tip0[b, c] = s.g_tip[b, c]


# ------------------------------------------------------------------------------------------------
# kernels
# ------------------------------------------------------------------------------------------------


@cuda.jit
def _command_kernel(p, ts, s, actions):
    """Actions (B,2) in [-1, 1] (clipped) -> the jaw's force set-point or closing speed, the pull speed."""
    b = cuda.grid(1)
    if b >= ts.mu.shape[0]:
        return
    a0 = min(max(float(actions[b, 0]), -1.0), 1.0)
    a1 = min(max(float(actions[b, 1]), -1.0), 1.0)
    ts.act[b, 0] = a0
    ts.act[b, 1] = a1
    if p.jaw_mode == JAW_FORCE:  # the jaw motor's 1 kHz force loop tracks the set-point
        s.g_force[b, G_SETPOINT] = (0.5 * (a0 + 1.0)) ** p.pinch_exp * p.max_force
        s.g_force[b, G_GAIN] = p.loop_gain
        s.g_force[b, G_VMAX] = p.max_close
    else:
        s.g_vradius[b] = -(a0 * p.max_close)
    if p.pull_mode == PULL_TRAVEL:  # the arm's position loop, speed-limited
        target = 0.5 * (a1 + 1.0) * p.max_travel
        ts.travel_target[b] = target
        speed = min(max((target - _travel(p, ts, s, b)) / p.agent_dt, -p.max_pull), p.max_pull)
    elif p.pull_mode == PULL_FORWARD:
        speed = 0.5 * (a1 + 1.0) * p.max_pull
    else:
        speed = a1 * p.max_pull
    for c in range(3):
        s.g_vpull[b, c] = p.pull_dir[c] * speed


@cuda.jit
def _task_kernel(m, s, out, p, ts, rng):
    """After the physics: finiteness and the smallest tet volume ratio (block-parallel), then env b's update."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0]:
        return
    tid = cuda.threadIdx.x
    nth = cuda.blockDim.x
    lo_sh = cuda.shared.array(THREADS_PER_BLOCK, np.float64)
    ok_sh = cuda.shared.array(THREADS_PER_BLOCK, np.int32)
    ok = 1
    for i in range(tid, s.x.shape[1], nth):
        for c in range(3):
            if not (math.isfinite(s.x[b, i, c]) and math.isfinite(s.v[b, i, c])):
                ok = 0
    lo = math.inf
    for t in range(tid, m.tets.shape[0], nth):
        r = _tet_edges(s.x[b], m.tets, t)[9] / m.rest_volume[t]
        if r < lo:  # (as forces.min_volume_ratios compares)
            lo = r
    lo_sh[tid] = lo
    ok_sh[tid] = ok
    cuda.syncthreads()
    if tid == 0:
        for k in range(1, nth):
            if lo_sh[k] < lo:
                lo = lo_sh[k]
            ok = ok & ok_sh[k]
        _task_update(p, s, out, ts, rng, b, ok == 1, lo)


@cuda.jit
def _reset_kernel(m, s, out, p, ts, rng, mask):
    """New episodes for the envs where ``mask``: the settled tissue, open jaws, drawn friction, scales and
    pose, cleared task state and the first observation frame (no sensor noise, as on the CPU)."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0] or not mask[b]:
        return
    tid = cuda.threadIdx.x
    nth = cuda.blockDim.x
    for i in range(tid, s.x.shape[1], nth):
        for c in range(3):
            s.x[b, i, c] = p.x_start[i, c]
            s.v[b, i, c] = 0.0
            s.f_ext[b, i, c] = 0.0
            out.contact_force[b, i, c] = 0.0
        out.contact_state[b, i] = 0
    for e in range(tid, s.fv.shape[1], nth):
        s.fv[b, e] = p.fv_start[e]
        s.dl_prev[b, e] = p.dl_start[e]
    cuda.syncthreads()
    if tid != 0:
        return
    s.t[b] = 0.0
    s.g_radius[b] = p.start_radius
    s.g_vradius[b] = 0.0
    for c in range(3):
        s.g_vpull[b, c] = 0.0
        out.anchor_out[b, c] = 0.0
        for col in range(out.jaw_out.shape[2]):
            out.jaw_out[b, c, col] = 0.0
    s.g_force[b, G_SETPOINT] = -1.0
    s.g_force[b, G_PINCH] = 0.0
    if p.jaw_mode == JAW_FORCE:  # the jaw motor starts in force control at zero force (jaws at rest)
        s.g_force[b, G_SETPOINT] = 0.0
        s.g_force[b, G_GAIN] = p.loop_gain
        s.g_force[b, G_VMAX] = p.max_close
    _draw_episode(p, s, ts, rng, b)
    for c in range(3):
        ts.region0[b, c] = _region_mean(p, s, b, c)
    ts.steps[b] = 0
    ts.prev_action[b, 0] = 0.0
    ts.prev_action[b, 1] = 0.0
    ts.lift[b] = 0.0
    ts.best_lift[b] = 0.0
    ts.grip[b] = 0.0
    ts.slip_total[b] = 0.0
    ts.lift_slip[b] = 0.0
    ts.hold_time[b] = 0.0
    ts.hold_slip[b] = 0.0
    ts.peak_pinch[b] = 0.0
    ts.peak_stress[b] = 0.0
    ts.lift_started[b] = False
    ts.hold_progress[b] = 0.0
    ts.travel_target[b] = 0.0
    _observe(p, s, out, ts, b, 0.0, 0.0, 0.0, True)


# ------------------------------------------------------------------------------------------------
# host side
# ------------------------------------------------------------------------------------------------


def task_params(core: GraspLiftCore) -> TaskParams:
    """The task constants of a (CPU) core's config and scene."""
    cfg = core.config
    rnd = cfg.randomization
    w = cfg.reward
    scene = core.scene
    model = scene.model
    return TaskParams(
        region=np.ascontiguousarray(core.region, dtype=np.int64), nominal=core.nominal_contacts.copy(),
        x_start=np.ascontiguousarray(scene.x_start), fv_start=np.ascontiguousarray(scene.fv_start),
        dl_start=elongations(scene.x_start, model.edges, model.rest_length),
        pose_tip=np.asarray(scene.pose.tip, dtype=np.float64), pose_axis=np.asarray(scene.pose.axis, dtype=np.float64),
        pose_e1=np.asarray(scene.pose.e1, dtype=np.float64),
        pull_dir=np.asarray(scene.pull_direction, dtype=np.float64),
        priv_nodes=np.ascontiguousarray(core.priv_nodes, dtype=np.int64),
        start_radius=float(core.start_radius), max_close=float(core.max_close), max_pull=float(core.max_pull),
        agent_dt=float(cfg.agent_dt_s), jaw_mode=JAW_FORCE if cfg.jaw_action == "force" else JAW_SPEED,
        pull_mode={"travel": PULL_TRAVEL, "speed": PULL_SPEED, "forward_speed": PULL_FORWARD}[cfg.pull_action],
        max_force=float(cfg.max_pinch_force_N), pinch_exp=float(cfg.pinch_action_exponent),
        loop_gain=float(cfg.force_loop_gain_m_s_per_N), max_travel=float(cfg.max_travel_m),
        obs_history=int(cfg.obs_history), frame_dim=int(core.frame_dim), privileged=bool(cfg.privileged_obs),
        lift_target=float(cfg.lift_target_m), hold_time=float(cfg.hold_time_s),
        hold_slip_tol=float(cfg.hold_slip_tolerance_m), lift_slip_tol=float(cfg.lift_slip_tolerance_m),
        time_limit=float(cfg.time_limit_s), max_steps=int(cfg.max_episode_steps), ref_force=float(cfg.reference_force_N),
        damage_stress=float(cfg.damage_stress_pa), terminate_on_damage=bool(cfg.terminate_on_damage),
        lift_started_m=float(cfg.lift_started_m), inverted_is_failure=bool(cfg.inverted_tet_is_failure),
        w_progress=float(w.progress), w_hold=float(w.hold), w_grasp=float(w.grasp), grasp_force=float(w.grasp_force_N),
        w_slip_mm=float(w.slip_per_mm), w_force=float(w.force_per_s), w_peak=float(w.peak_force),
        peak_as_made=w.peak_force_timing == "as_made",
        peak_mu_ref=float(w.peak_force_mu_ref) if w.peak_force_mu_ref is not None else 0.0,
        w_damage=float(w.damage), w_success=float(w.success_bonus), w_failure=float(w.failure_penalty),
        mu_lo=float(rnd.mu_range[0]), mu_hi=float(rnd.mu_range[1]), mu_log=rnd.mu_distribution == "log_uniform",
        ks_lo=float(rnd.stiffness_scale_range[0]), ks_hi=float(rnd.stiffness_scale_range[1]),
        ms_lo=float(rnd.mass_scale_range[0]), ms_hi=float(rnd.mass_scale_range[1]),
        pose_offset=float(rnd.pose_offset_m), pose_tilt=math.radians(rnd.pose_tilt_deg),
        pose_azimuth=math.radians(rnd.pose_azimuth_deg), noise_std=float(rnd.sensor_noise_N),
    )


def _task_state(batch: int, obs_history: int, frame_dim: int) -> TaskState:
    """Host arrays of a fresh task state (zeros; nothing pinned)."""
    f, i, z = np.float64, np.int64, np.bool_
    shapes: dict[str, tuple[tuple[int, ...], Any]] = {
        "tip0": ((batch, 3), f), "region0": ((batch, 3), f), "steps": ((batch,), i), "act": ((batch, 2), f),
        "prev_action": ((batch, 2), f), "lift_started": ((batch,), z), "frames": ((batch, obs_history, frame_dim), f),
        "obs": ((batch, obs_history * frame_dim), np.float32), "terminal_obs": ((batch, obs_history * frame_dim), np.float32),
        "terms": ((batch, len(REWARD_TERMS)), f), "episode_length": ((batch,), i), "draws": ((batch, len(DRAW_COLUMNS)), f),
        "pin": ((batch, len(GPU_PINNABLE)), f),
    }
    flags = ("terminated", "truncated", "done", "is_success", "lost_grasp", "slipped", "damaged", "numerical_failure")
    arrays = {}
    for name in TaskState._fields:
        shape, dtype = shapes.get(name, ((batch,), z if name in flags else f))
        arrays[name] = np.zeros(shape, dtype=dtype)
    arrays["pin"][:] = np.nan
    return TaskState(**arrays)


def as_torch(array):
    """A torch tensor of a device array: a zero-copy view on a GPU (``__cuda_array_interface__``), a copy
    on the host under numba's CUDA simulator (which has no device memory to share)."""
    import torch

    if hasattr(array, "__cuda_array_interface__") and torch.cuda.is_available():
        return torch.as_tensor(array, device="cuda")
    return torch.from_numpy(array.copy_to_host())


class CudaGraspLiftCore:
    """The GraspLift task for ``num_envs`` tissues resident on the GPU (see the module docstring).

    ``precision="float32"`` keeps the tissue's per-node, per-spring and per-tet arrays in float32
    (:data:`~msdgrasp.physics.cuda_step.FLOAT32_FIELDS`); the task's own state stays float64.

    ``reset()`` starts every env; ``step(actions)`` advances all of them by one agent step and resets the
    ones that ended. Both return the device arrays ``(obs, reward, terminated, truncated)``: the same
    arrays every call, updated in place. Every other output (``terminal_obs``, the info flags, the reward
    terms, the draws) is a field of :meth:`arrays`; :meth:`download` copies named fields to the host.
    """

    def __init__(self, config: GraspLiftConfig | None = None, num_envs: int = 1, seed: int = 0,
                 threads: int = THREADS_PER_BLOCK, precision: str = "float64") -> None:
        check_range("threads", threads, 1, THREADS_PER_BLOCK)
        check_choice("precision", precision, PRECISIONS)
        # the CPU core builds the scene, the simulation's host arrays and the task's constants once
        self.host = host = GraspLiftCore(config, num_envs)
        self.config = host.config
        self.num_envs = host.num_envs
        self.frame_dim = host.frame_dim
        self.obs_dim = host.obs_dim
        self.threads = int(threads)
        self.precision = precision
        sim = host.sim
        self.physics = CudaBatch(sim.kernel_model(), sim.kernel_state(), sim.kernel_readout(), threads=self.threads,
                                 precision=precision)
        self.params = to_device(task_params(host))
        self.state = to_device(_task_state(self.num_envs, self.config.obs_history, self.frame_dim))
        with warnings.catch_warnings():  # the simulator compiles the state set-up in object mode, noisily
            warnings.simplefilter("ignore")
            self.rng = create_xoroshiro128p_states(self.num_envs, seed=int(seed))
        self._all = cuda.to_device(np.ones(self.num_envs, dtype=np.bool_))
        self._blocks = (self.num_envs + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK

    # -- the loop -------------------------------------------------------------------------------
    def reset(self, options: dict[str, Any] | None = None):
        """Start a new episode in every env. ``options`` pins ``mu``, ``stiffness_scale`` and ``mass_scale``
        (a number or one per env) for this and every later episode until the next ``reset``."""
        options = dict(options or {})
        unknown = sorted(set(options) - set(GPU_PINNABLE))
        if unknown:
            raise ConfigError(f"reset options: unknown key(s) {unknown}; allowed on the GPU: {list(GPU_PINNABLE)}")
        sim = self.host.sim
        bounds = {"mu": (0.0, 10.0), "stiffness_scale": (0.0, sim.max_stiffness_scale),
                  "mass_scale": (sim.min_mass_scale, None)}
        pin = np.full((self.num_envs, len(GPU_PINNABLE)), np.nan)
        for k, name in enumerate(GPU_PINNABLE):
            if name in options:
                values = np.broadcast_to(np.asarray(options[name], dtype=np.float64), (self.num_envs,))
                for v in np.unique(values):
                    check_range(f"options[{name!r}]", float(v), *bounds[name], lo_inclusive=name != "stiffness_scale")
                pin[:, k] = values
        self.state.pin.copy_to_device(pin)
        m, s, out = self.physics.model, self.physics.state, self.physics.out
        _reset_kernel[self.num_envs, self.threads](m, s, out, self.params, self.state, self.rng, self._all)
        return self.state.obs

    def step(self, actions):
        """Advance every env by one agent step; ``actions`` (B,2) in [-1, 1] (clipped): a host array, a
        device array or a CUDA tensor (read in place). Envs that end are reset in the same call."""
        shape = tuple(getattr(actions, "shape", np.shape(actions)))
        if shape != (self.num_envs, 2):
            raise ConfigError(f"actions must have shape ({self.num_envs}, 2), got {shape}")
        if hasattr(actions, "__cuda_array_interface__"):
            dev = cuda.as_cuda_array(actions)
        else:
            host = actions.numpy() if hasattr(actions, "numpy") else np.asarray(actions)
            dev = cuda.to_device(np.ascontiguousarray(host, dtype=np.float64))
        m, s, out = self.physics.model, self.physics.state, self.physics.out
        _command_kernel[self._blocks, THREADS_PER_BLOCK](self.params, self.state, s, dev)
        self.physics.step(self.config.physics_steps_per_action)
        _task_kernel[self.num_envs, self.threads](m, s, out, self.params, self.state, self.rng)
        _reset_kernel[self.num_envs, self.threads](m, s, out, self.params, self.state, self.rng, self.state.done)
        st = self.state
        return st.obs, st.reward, st.terminated, st.truncated

    # -- access ---------------------------------------------------------------------------------
    def arrays(self) -> dict[str, object]:
        """Every device array of the task, the physics state and the readouts, by field name (no copy)."""
        return {**self.physics.arrays(), **{name: getattr(self.state, name) for name in TaskState._fields}}

    def download(self, *names: str) -> dict[str, np.ndarray]:
        """Host copies of the named fields of :meth:`arrays`."""
        arrays = self.arrays()
        unknown = [n for n in names if n not in arrays]
        if unknown:
            raise ConfigError(f"unknown field(s) {unknown}; allowed: {sorted(arrays)}")
        return {n: arrays[n].copy_to_host() for n in names}
