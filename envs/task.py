"""The GraspLift task per env, written once for both backends: scalar numba functions over records.

One source, two targets (as the physics' contact law): the CPU core (:class:`.core.GraspLiftCore`) calls
these functions in ``@kernel`` loops over its envs, the GPU core (:mod:`.cuda_core`) compiles the same Python
source for the device (:func:`~msdgrasp.physics.cuda_step.device_twin`) and calls them per env from its
kernels. They use scalar arithmetic and loops only, and write into preallocated arrays:

* :func:`command`: actions -> the jaw's pinch set-point (or closing speed) and the pull speed;
* :func:`update`: after the physics, lift, slip, hold, reward terms, flags and the observation;
* :func:`observe`: the observation frame and its history;
* :func:`draw_episode` and :func:`begin_episode`: the non-random part of a reset (an episode's raw random
  numbers -> friction, scales and pose; cleared episode state; the first frame).

What they read and write, passed whole:

* :class:`TaskParams`: the task's constants. The config itself travels as a record *derived* from the
  config dataclasses (:func:`config_record`: one NamedTuple per dataclass, field for field, nested records
  for nested configs; a choice ``name: Literal["a", "b"]`` becomes one flag per option, ``name_a`` and
  ``name_b``; ``None`` becomes NaN; strings, which the task does not read, are left out), so a new config
  field needs no code here. Only what the scene and grasper derive (start radius, grasp region, ...) is
  listed by hand.
* :class:`TaskState`: the per-env episode state and the step's outputs, batch first.

The random numbers are each backend's own: a reset fills ``draws[b]`` with raw variates (uniform on [0, 1)
or standard normal, ``TaskParams.draw_is_normal``: the declared perturbations', :mod:`.perturbations`) and the sensor
noise into ``noise[b]``; the CPU from NumPy's
per-env generators, the GPU from xoroshiro streams. Everything after the draw is shared.

The GPU twins bind the numba functions each one calls to their own twins (``device_twin``). The last three
(``command_batch``, ``update_batch``, ``start_episode``) are the CPU core's loops.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import types
import typing
from typing import Any, Literal, NamedTuple

import numpy as np
from ..physics.jit import kernel

from ..physics.contact import (
    G_GAIN, G_PINCH, G_SETPOINT, G_VMAX, J_CONTACT, J_NORMAL, J_PEAK_PRESSURE, J_SLIP, J_SLIP_DIST, J_TX, J_TY, J_TZ,
    jaw_reach, jaw_start_radius,
)
from ..physics.numba_cache import key_on_physics
from ..physics.viscoelastic import elongations
from .perturbations import (
    CONSTANT, CUBE_ROOT, LOG_UNIFORM, MAX_LATENCY_STEPS, STEPS, SYMMETRIC, UNIFORM, column_index, draw_columns,
    draw_plan,
)

# the kernels below compile in the readout columns J_* and G_* of physics/contact.py
key_on_physics(__file__)

#: one observation frame (a stacked history repeats it, oldest first); privileged entries follow these
OBS_NAMES = (
    "jaw_opening", "jaw_speed", "pull_distance", "pull_speed",
    "normal_force_0", "normal_force_1", "normal_force_2",
    "tangential_force_0", "tangential_force_1", "tangential_force_2",
    "contact_fraction_0", "contact_fraction_1", "contact_fraction_2",
    "slip_speed_0", "slip_speed_1", "slip_speed_2",
    "slipping_fraction_0", "slipping_fraction_1", "slipping_fraction_2",
    "prev_action_jaw", "prev_action_pull", "time_fraction",
    "lift_progress", "hold_progress", "hold_slip", "lift_lag", "peak_pinch", "best_lift",
    "friction_use_0", "friction_use_1", "friction_use_2", "lift_slip",
)
#: position of each observation entry in a frame
OBS = {name: i for i, name in enumerate(OBS_NAMES)}


def obs_group(prefix: str) -> slice:
    """The frame positions of a per-jaw group (``prefix_0`` .. ``prefix_2``, adjacent)."""
    first = OBS[f"{prefix}_0"]
    if [OBS.get(f"{prefix}_{k}") for k in range(3)] != [first, first + 1, first + 2]:
        raise ValueError(f"observation group {prefix!r} is not three adjacent entries")
    return slice(first, first + 3)


# frame positions the kernels write (module integers: numba compiles them as constants)
(I_OPENING, I_JAW_SPEED, I_TRAVEL, I_PULL_SPEED, I_PREV_ACTION, I_TIME, I_LIFT, I_HOLD, I_HOLD_SLIP, I_LIFT_LAG,
 I_PEAK_PINCH, I_BEST_LIFT, I_LIFT_SLIP) = (OBS[n] for n in (
    "jaw_opening", "jaw_speed", "pull_distance", "pull_speed", "prev_action_jaw", "time_fraction", "lift_progress",
    "hold_progress", "hold_slip", "lift_lag", "peak_pinch", "best_lift", "lift_slip"))
assert OBS["prev_action_pull"] == I_PREV_ACTION + 1
(I_NORMAL, I_TANGENTIAL, I_CONTACT, I_SLIP_SPEED, I_SLIPPING, I_FRICTION_USE) = (obs_group(n).start for n in (
    "normal_force", "tangential_force", "contact_fraction", "slip_speed", "slipping_fraction", "friction_use"))
N_OBS = len(OBS_NAMES)

#: the reward terms (``info["reward_terms"]`` keys; columns of ``TaskState.terms``)
REWARD_TERMS = ("progress", "hold", "grasp", "slip", "force", "peak_force", "setpoint_change", "damage", "success",
                "failure")
(R_PROGRESS, R_HOLD, R_GRASP, R_SLIP, R_FORCE, R_PEAK_FORCE, R_SETPOINT_CHANGE, R_DAMAGE, R_SUCCESS, R_FAILURE) = (
    REWARD_TERMS.index(n) for n in REWARD_TERMS)

#: an episode's random draws (``TaskState.draws``): the declared perturbations' columns (.perturbations); the
#: positions of the built-in columns the task's effects read (module integers: numba compiles them as constants)
D_MU, D_KS, D_MS, D_OFFSET_DIR, D_OFFSET_R, D_TILT_AXIS, D_TILT, D_AZIMUTH, D_TIP_OFFSET, D_AXIS_CHANGE, D_E1_CHANGE, \
    D_BIAS, D_LATENCY, D_GAIN, D_NOISE = (column_index(n) for n in (
        "mu", "stiffness_scale", "mass_scale", "offset_dir_x", "offset_r", "tilt_axis_x", "tilt", "azimuth",
        "tip_offset_x", "axis_change_x", "jaw_dir_change_x", "force_bias_0", "latency", "force_loop_gain",
        "sensor_noise"))
#: per-step noise columns of ``TaskState.noise``, drawn in this order where :func:`noise_scale` draws them: the three
#: jaws' force readings (N), their slip speeds (the arm's top speed), (with ``force_noise: vector``) their tangential
#: readings' noise along the tangential force and across it (N), then (with ``sensed_task_state``) the slipping
#: shares' noise and the lift tracker's (m)
NOISE_COLUMNS = ("force_0", "force_1", "force_2", "slip_speed_0", "slip_speed_1", "slip_speed_2",
                 "tangential_along_0", "tangential_along_1", "tangential_along_2",
                 "tangential_across_0", "tangential_across_1", "tangential_across_2",
                 "slipping_0", "slipping_1", "slipping_2", "lift")
N_NOISE = len(NOISE_COLUMNS)
N_FORCE, N_SLIP_SPEED, N_ALONG, N_ACROSS, N_SLIPPING, N_LIFT = (NOISE_COLUMNS.index(n) for n in (
    "force_0", "slip_speed_0", "tangential_along_0", "tangential_across_0", "slipping_0", "lift"))
#: the longest delay of the lift tracker, agent steps (the length of its ring of measurements less one)
MAX_LIFT_DELAY_STEPS = 3
#: the task state as the sensors give it (``sensed_task_state``; columns of ``TaskState.sensed``): the tracked lift
#: (m, delayed), the highest tracked lift (m, capped at the target), the sensed slip since the arm's travel passed
#: ``lift_started_m`` (m), the time the tracked lift has been at the target (s), the sensed slip during that time
#: (m), the highest sum of the three normal-force readings (N)
SENSED = ("lift", "best_lift", "lift_slip", "hold_time", "hold_slip", "peak_pinch")
S_LIFT, S_BEST_LIFT, S_LIFT_SLIP, S_HOLD_TIME, S_HOLD_SLIP, S_PEAK_PINCH = range(len(SENSED))
#: the ground truth behind the sensed task-state entries, for critics and teachers (privileged, with
#: ``sensed_task_state``), each in its sensed entry's units
PRIVILEGED_TRUTH = ("true_lift_progress", "true_hold_progress", "true_hold_slip", "true_lift_lag", "true_peak_pinch",
                    "true_best_lift", "true_lift_slip", "true_slip_speed_0", "true_slip_speed_1", "true_slip_speed_2",
                    "true_slipping_fraction_0", "true_slipping_fraction_1", "true_slipping_fraction_2")
N_PRIVILEGED_TRUTH = len(PRIVILEGED_TRUTH)

#: what a reset may pin (columns of ``TaskState.pin``; NaN: drawn, or the config's pose jitter)
PINNABLE = ("mu", "mu_kinetic", "stiffness_scale", "mass_scale", "pose_offset_m", "pose_tilt_deg", "pose_azimuth_deg")
P_MU, P_MU_KINETIC, P_KS, P_MS, P_OFFSET, P_TILT, P_AZIMUTH = range(len(PINNABLE))


# ------------------------------------------------------------------------------------------------
# records
# ------------------------------------------------------------------------------------------------


def _kind(hint: Any) -> Any:
    """What a config field becomes in its record: bool, int, float, "tuple", "choice", "record" or None (left out)."""
    origin = typing.get_origin(hint)
    if origin is typing.Annotated:
        return _kind(typing.get_args(hint)[0])
    if origin in (typing.Union, types.UnionType):
        kinds = {_kind(a) for a in typing.get_args(hint) if a is not type(None)}
        return None if None in kinds else (kinds.pop() if len(kinds) == 1 else float)
    if origin is Literal:
        return "choice"
    if origin is tuple:
        return "tuple"
    if dataclasses.is_dataclass(hint):
        return "record"
    return {bool: bool, int: int, float: float}.get(hint)


_RECORD_TYPES: dict[type, tuple[type, tuple]] = {}


def _record_type(cls: type) -> tuple[type, tuple]:
    """The record class of config dataclass ``cls`` and how each of its fields converts (made once)."""
    if cls not in _RECORD_TYPES:
        hints = typing.get_type_hints(cls, include_extras=True)
        plan = []
        for f in dataclasses.fields(cls):
            kind = _kind(hints[f.name])
            if kind == "choice":
                options = typing.get_args(_strip_annotated(hints[f.name]))
                plan.append((f.name, kind, tuple(f"{f.name}_{o}" for o in options), options))
            elif kind is not None:
                plan.append((f.name, kind, (f.name,), hints[f.name]))
        name = f"{cls.__name__}Record"
        record = collections.namedtuple(name, [n for entry in plan for n in entry[2]])
        record.__module__ = __name__
        globals()[name] = record  # importable by name: numba's cache pickles the type by reference
        _RECORD_TYPES[cls] = (record, tuple(plan))
    return _RECORD_TYPES[cls]


def _strip_annotated(hint: Any) -> Any:
    return _strip_annotated(typing.get_args(hint)[0]) if typing.get_origin(hint) is typing.Annotated else hint


def config_record(config: Any) -> tuple:
    """The config dataclass ``config`` as a numba-readable record (see the module docstring)."""
    record, plan = _record_type(type(config))
    values: list[Any] = []
    for name, kind, _, extra in plan:
        v = getattr(config, name)
        if kind == "choice":
            values.extend(v == o for o in extra)
        elif kind == "record":
            values.append(config_record(v))
        elif kind == "tuple":
            values.append(tuple(float(x) for x in v))
        else:
            values.append(math.nan if v is None else kind(v))
    return record(*values)


class TaskParams(NamedTuple):
    """The task's constants (SI units): the config record and what the scene and grasper derive."""

    env: Any  # config_record(GraspLiftConfig): .reward and .randomization nested
    region: np.ndarray  # (R,) int: surface nodes the jaws may hold (their mean is the lift)
    nominal: np.ndarray  # (3,) nominal contact nodes per jaw (contact fraction normaliser)
    x_start: np.ndarray  # (N,3) m settled positions (where every episode starts)
    fv_start: np.ndarray  # (E,) N settled Maxwell forces
    dl_start: np.ndarray  # (E,) m settled spring elongations
    pose_tip: np.ndarray  # (3,) m nominal grasp pose
    pose_axis: np.ndarray  # (3,)
    pose_e1: np.ndarray  # (3,)
    pull_dir: np.ndarray  # (3,)
    priv_nodes: np.ndarray  # (P,) int nodes of the privileged displacement observation
    draw_is_normal: np.ndarray  # (D,) bool: each draw column's raw variate standard normal (else uniform)
    draw_law: np.ndarray  # (D,) int: each draw column's law (.perturbations.LAWS)
    draw_a: np.ndarray  # (D,) its law's first parameter
    draw_b: np.ndarray  # (D,) its law's second parameter
    priv_col: np.ndarray  # (K,) int: the draw column of each privileged perturbation entry
    priv_centre: np.ndarray  # (K,) its centre
    priv_scale: np.ndarray  # (K,) its scale
    clear_radius: float  # m jaw radius clear of the tissue at the planned pose (the opening observation's scale)
    open_radius: float  # m the grasper's widest opening
    jaw_length: float  # m
    jaw_half_width: float  # m
    surface: np.ndarray  # (S,) int surface nodes (the jaws' footprints)
    max_close: float  # m/s jaw closing speed limit
    max_pull: float  # m/s arm speed limit
    agent_dt: float  # s
    max_steps: int  # agent steps of the time limit
    frame_dim: int  # entries per observation frame


def task_params(core: Any) -> TaskParams:
    """The task constants of a CPU core's (:class:`.core.GraspLiftCore`) config and scene."""
    cfg, scene = core.config, core.scene
    vec = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    return TaskParams(
        env=config_record(cfg), region=np.ascontiguousarray(core.region, dtype=np.int64),
        nominal=vec(core.nominal_contacts), x_start=vec(scene.x_start), fv_start=vec(scene.fv_start),
        dl_start=elongations(scene.x_start, scene.model.edges, scene.model.rest_length),
        pose_tip=vec(scene.pose.tip), pose_axis=vec(scene.pose.axis), pose_e1=vec(scene.pose.e1),
        pull_dir=vec(scene.pull_direction), priv_nodes=np.ascontiguousarray(core.priv_nodes, dtype=np.int64),
        **draw_plan(cfg.randomization), clear_radius=float(core.scene.start_radius),
        open_radius=float(core.scene.grasper.open_radius_m), jaw_length=float(core.scene.grasper.jaw_length_m),
        jaw_half_width=0.5 * float(core.scene.grasper.jaw_width_m),
        surface=np.ascontiguousarray(core.scene.mesh.surface_nodes, dtype=np.int64),
        max_close=float(core.max_close),
        max_pull=float(core.max_pull), agent_dt=float(cfg.agent_dt_s), max_steps=int(cfg.max_episode_steps),
        frame_dim=int(core.frame_dim),
    )


class TaskState(NamedTuple):
    """Per-env episode state and the step's outputs, batch first."""

    mu: np.ndarray  # (B,) static friction of the episode
    tip0: np.ndarray  # (B,3) m grasper tip at the episode start
    region0: np.ndarray  # (B,3) m grasp region's mean at the episode start
    steps: np.ndarray  # (B,) int agent steps in the episode
    act: np.ndarray  # (B,2) this step's clipped action
    prev_action: np.ndarray  # (B,2)
    lift: np.ndarray  # (B,) m
    best_lift: np.ndarray  # (B,) m
    grip: np.ndarray  # (B,) pinch / grasp_force_N, at most 1
    slip_total: np.ndarray  # (B,) m
    lift_slip: np.ndarray  # (B,) m slip since lifting began
    hold_time: np.ndarray  # (B,) s
    hold_slip: np.ndarray  # (B,) m
    peak_pinch: np.ndarray  # (B,) N
    peak_stress: np.ndarray  # (B,) Pa
    lift_started: np.ndarray  # (B,) bool
    time_to_lift: np.ndarray  # (B,) s to the lift target (NaN: not yet)
    hold_progress: np.ndarray  # (B,)
    travel_target: np.ndarray  # (B,) m
    frames: np.ndarray  # (B,H,F) observation history, oldest first
    obs: np.ndarray  # (B,H*F) the observation (on the GPU float32, and a new episode's first where done)
    terminal_obs: np.ndarray  # (B,H*F) the last observation of an episode that ended this step
    reward: np.ndarray  # (B,)
    terms: np.ndarray  # (B,len(REWARD_TERMS)) reward terms
    terminated: np.ndarray  # (B,) bool
    truncated: np.ndarray  # (B,) bool
    done: np.ndarray  # (B,) bool: terminated | truncated
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
    draws: np.ndarray  # (B,D) this episode's random draws (.perturbations.draw_columns)
    pin: np.ndarray  # (B,len(PINNABLE)) pinned values (NaN: drawn)
    noise: np.ndarray  # (B,N_NOISE) this step's sensor noise (NOISE_COLUMNS)
    sensed: np.ndarray  # (B,len(SENSED)) the task state as the sensors give it (sensed_task_state)
    lift_track: np.ndarray  # (B,MAX_LIFT_DELAY_STEPS+1) m the lift tracker's measurements, newest first
    queue: np.ndarray  # (B,MAX_LATENCY_STEPS+1,2) the actions sent, newest first (what a latency delays)
    readings: np.ndarray  # (B,6) N: the low-pass filtered normal, then tangential, force readings (force_filter_s)


def task_state(batch: int, obs_history: int, frame_dim: int, obs_dtype: Any = np.float64) -> TaskState:
    """Host arrays of a fresh task state (zeros; nothing pinned)."""
    f, i, z = np.float64, np.int64, np.bool_
    shapes: dict[str, tuple[tuple[int, ...], Any]] = {
        "tip0": ((batch, 3), f), "region0": ((batch, 3), f), "steps": ((batch,), i), "act": ((batch, 2), f),
        "prev_action": ((batch, 2), f), "frames": ((batch, obs_history, frame_dim), f),
        "obs": ((batch, obs_history * frame_dim), obs_dtype),
        "terminal_obs": ((batch, obs_history * frame_dim), obs_dtype),
        "terms": ((batch, len(REWARD_TERMS)), f), "episode_length": ((batch,), i),
        "draws": ((batch, len(draw_columns())), f), "pin": ((batch, len(PINNABLE)), f), "noise": ((batch, N_NOISE), f),
        "sensed": ((batch, len(SENSED)), f), "lift_track": ((batch, MAX_LIFT_DELAY_STEPS + 1), f),
        "queue": ((batch, MAX_LATENCY_STEPS + 1, 2), f), "readings": ((batch, 6), f),
    }
    flags = ("lift_started", "terminated", "truncated", "done", "is_success", "lost_grasp", "slipped", "damaged",
             "numerical_failure")
    arrays = {name: np.zeros(*shapes.get(name, ((batch,), z if name in flags else f))) for name in TaskState._fields}
    arrays["pin"][:] = np.nan
    arrays["time_to_lift"][:] = np.nan
    return TaskState(**arrays)


# ------------------------------------------------------------------------------------------------
# per-env functions (leaves first)
# ------------------------------------------------------------------------------------------------


@kernel
def pinned(value, default):
    """``value`` unless it is NaN (not pinned)."""
    return default if math.isnan(value) else value


@kernel
def peak_charge_points(w, reference_force_N, peak_pinch, weight):
    """The peak-force charge, points, of an episode whose peak pinch is ``peak_pinch`` N (``w``: the reward record;
    ``weight``: the friction scaling), its slope times ``w.peak_force_beyond_knee`` above ``w.peak_force_knee``
    points where that is set (not NaN)."""
    charge = w.peak_force * (peak_pinch * weight) / reference_force_N
    if math.isnan(w.peak_force_knee):
        return charge
    return min(charge, w.peak_force_knee) + w.peak_force_beyond_knee * max(charge - w.peak_force_knee, 0.0)


@kernel
def rotate(v0, v1, v2, k0, k1, k2, ang):
    """Rodrigues rotation of v about the unit axis k."""
    c = math.cos(ang)
    sn = math.sin(ang)
    kv = k0 * v0 + k1 * v1 + k2 * v2
    return (v0 * c + (k1 * v2 - k2 * v1) * sn + k0 * kv * (1 - c),
            v1 * c + (k2 * v0 - k0 * v2) * sn + k1 * kv * (1 - c),
            v2 * c + (k0 * v1 - k1 * v0) * sn + k2 * kv * (1 - c))


@kernel
def perturb_pose(tip, axis, e1, d, offset_m, tilt_rad, azimuth_rad, tip_out, axis_out, e1_out):
    """The grasp pose moved by an episode's draws ``d`` (draw columns): the tip moves up to ``offset_m``
    normal to the axis (radius drawn as in a ball), the axis tilts up to ``tilt_rad`` about a random normal,
    and the jaws turn up to ``azimuth_rad`` about the new axis."""
    a0, a1, a2 = axis[0], axis[1], axis[2]
    n0, n1, n2 = d[D_OFFSET_DIR], d[D_OFFSET_DIR + 1], d[D_OFFSET_DIR + 2]
    da = n0 * a0 + n1 * a1 + n2 * a2
    e0, e1_, e2 = n0 - a0 * da, n1 - a1 * da, n2 - a2 * da
    nrm = math.sqrt(e0 * e0 + e1_ * e1_ + e2 * e2) + 1e-12
    r = offset_m * d[D_OFFSET_R]
    tip_out[0] = tip[0] + r * (e0 / nrm)
    tip_out[1] = tip[1] + r * (e1_ / nrm)
    tip_out[2] = tip[2] + r * (e2 / nrm)
    m0, m1, m2 = d[D_TILT_AXIS], d[D_TILT_AXIS + 1], d[D_TILT_AXIS + 2]
    t0, t1, t2 = a1 * m2 - a2 * m1, a2 * m0 - a0 * m2, a0 * m1 - a1 * m0
    nrm = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2) + 1e-12
    t0, t1, t2 = t0 / nrm, t1 / nrm, t2 / nrm
    ang = tilt_rad * d[D_TILT]
    x0, x1, x2 = rotate(a0, a1, a2, t0, t1, t2, ang)
    f0, f1, f2 = rotate(e1[0], e1[1], e1[2], t0, t1, t2, ang)
    f0, f1, f2 = rotate(f0, f1, f2, x0, x1, x2, azimuth_rad * d[D_AZIMUTH])
    axis_out[0], axis_out[1], axis_out[2] = x0, x1, x2
    e1_out[0], e1_out[1], e1_out[2] = f0, f1, f2


@kernel
def travel(p, s, ts, b):
    """Grasper pull distance of env b along the pull direction since the episode start, m."""
    return ((s.g_tip[b, 0] - ts.tip0[b, 0]) * p.pull_dir[0] + (s.g_tip[b, 1] - ts.tip0[b, 1]) * p.pull_dir[1]
            + (s.g_tip[b, 2] - ts.tip0[b, 2]) * p.pull_dir[2])


@kernel
def region_mean(p, x, b, c):
    """Mean coordinate c of env b's grasp region (summed in node order)."""
    acc = 0.0
    for q in range(p.region.shape[0]):
        acc += x[b, p.region[q], c]
    return acc / p.region.shape[0]


@kernel
def column_drawn(p, k):
    """Whether draw column k draws a raw variate at a reset: not where its law is a constant (an axis that is off) or
    derived, so the nominal task's random stream is what it was before the axis existed."""
    return p.draw_law[k] < CONSTANT


@kernel(inline="always")
def draw_value(law, a, b, u):
    """A draw column's value from its raw variate ``u`` by its law (.perturbations.LAWS) with parameters a, b."""
    if law == UNIFORM:
        return a + (b - a) * u
    if law == LOG_UNIFORM:
        lo = math.log(a)
        return math.exp(lo + (math.log(b) - lo) * u)
    if law == SYMMETRIC:
        return a + b * (-1.0 + 2.0 * u)
    if law == CUBE_ROOT:
        return u ** (1.0 / 3.0)
    if law == STEPS:
        return min(a + math.floor(u * (b - a + 1.0)), b)
    if law == CONSTANT:
        return a
    return u  # identity; a derived column: set when the episode starts


@kernel
def rest_action(env):
    """The action that leaves the grasper at rest: zero pinch (force) or no closing (speed), and no pull."""
    return (-1.0 if env.jaw_action_force else 0.0), (0.0 if env.pull_action_speed else -1.0)


@kernel
def shaped_fraction(a, exponent):
    """The fraction in [0, 1] of its range that action ``a`` in [-1, 1] commands: ((a + 1) / 2) ** exponent (an
    exponent above 1 spends more of the action range on the low end)."""
    return (0.5 * (a + 1.0)) ** exponent


@kernel
def pinch_setpoint(env, a):
    """Pinch-force set-point (N) of jaw action ``a`` in [-1, 1] (jaw_action = force); ``env``: the config record."""
    return shaped_fraction(a, env.pinch_action_exponent) * env.max_pinch_force_N


@kernel
def pull_speed_fraction(env, a):
    """Pull speed, a fraction of the arm's top speed, of pull action ``a`` in [-1, 1] (pull_action = forward_speed)."""
    return shaped_fraction(a, env.pull_action_exponent)


@kernel
def travel_setpoint(env, a):
    """Pull-distance set-point (m) of pull action ``a`` in [-1, 1] (pull_action = travel)."""
    return 0.5 * (a + 1.0) * env.max_travel_m


@kernel
def command(p, s, ts, b, a0, a1):
    """Env b's action (clipped to [-1, 1]) -> the jaw's force set-point or closing speed, and the pull speed."""
    e = p.env
    a0 = min(max(a0, -1.0), 1.0)
    a1 = min(max(a1, -1.0), 1.0)
    ts.act[b, 0] = a0
    ts.act[b, 1] = a1
    # the action queue, newest first: with a latency of k steps the action sent k steps ago takes effect
    q = ts.queue[b]
    for k in range(q.shape[0] - 1, 0, -1):
        q[k, 0] = q[k - 1, 0]
        q[k, 1] = q[k - 1, 1]
    q[0, 0] = a0
    q[0, 1] = a1
    lat = int(ts.draws[b, D_LATENCY])
    a0 = q[lat, 0]
    a1 = q[lat, 1]
    if e.jaw_action_force:  # the jaw motor's 1 kHz force loop tracks the set-point (up to the motor's limit)
        s.g_force[b, G_SETPOINT] = min(pinch_setpoint(e, a0), pinned(e.randomization.pinch_ceiling_N, math.inf))
        s.g_force[b, G_GAIN] = e.force_loop_gain_m_s_per_N * ts.draws[b, D_GAIN]
        s.g_force[b, G_VMAX] = p.max_close
    else:
        s.g_vradius[b] = -(a0 * p.max_close)
    if e.pull_action_travel:  # the arm's position loop: the set-point within the step if the speed limit allows
        target = travel_setpoint(e, a1)
        ts.travel_target[b] = target
        speed = min(max((target - travel(p, s, ts, b)) / p.agent_dt, -p.max_pull), p.max_pull)
    elif e.pull_action_forward_speed:
        speed = pull_speed_fraction(e, a1) * p.max_pull
    else:
        speed = a1 * p.max_pull
    for c in range(3):
        s.g_vpull[b, c] = p.pull_dir[c] * speed


@kernel
def noise_scale(p, ts, b, col):
    """The standard deviation of env b's noise column ``col`` (NOISE_COLUMNS) this step, or -1 where the column is
    not drawn (a sensor without noise draws nothing, so the nominal task's random stream is what it was before the
    sensor existed). One rule for both backends: each draws its normal variates for the drawn columns in order."""
    e = p.env
    r = e.randomization
    if col < N_SLIP_SPEED:
        return ts.draws[b, D_NOISE]  # (the episode's level; drawn even at 0)
    if col < N_ALONG:
        return r.slip_noise if r.slip_noise > 0.0 else -1.0
    if col < N_SLIPPING:
        return ts.draws[b, D_NOISE] if r.force_noise_vector else -1.0
    if col < N_LIFT:
        return r.slip_noise if (e.sensed_task_state and r.slip_sensing_exact and r.slip_noise > 0.0) else -1.0
    return r.lift_noise_m if (e.sensed_task_state and r.lift_sensing_tracked and r.lift_noise_m > 0.0) else -1.0


@kernel
def noise_scales(p, ts, scales):
    """:func:`noise_scale` of every env and column into ``scales`` (B, N_NOISE)."""
    for b in range(scales.shape[0]):
        for col in range(N_NOISE):
            scales[b, col] = noise_scale(p, ts, b, col)


@kernel
def sense_task_state(p, ts, b, fresh, pinch_read, slip_read, tr, lift_true):
    """Advance env b's task state as its sensors give it (``ts.sensed``, SENSED) by one frame: ``pinch_read`` the
    sum of the normal-force readings (N), ``slip_read`` the mean of the slip-speed readings (the arm's top speed),
    ``tr`` the arm encoder's travel (m), ``lift_true`` the grasped region's true lift (m), which the lift tracker
    measures with its noise and delay. ``fresh``: a new episode (everything from zero)."""
    e = p.env
    r = e.randomization
    sn = ts.sensed[b]
    ring = ts.lift_track[b]
    if fresh:
        for k in range(sn.shape[0]):
            sn[k] = 0.0
        for k in range(ring.shape[0]):
            ring[k] = 0.0
        return
    # the tracker: this frame's measurement enters the ring; the entry lift_delay_steps old is what it reports
    for k in range(ring.shape[0] - 1, 0, -1):
        ring[k] = ring[k - 1]
    ring[0] = lift_true + ts.noise[b, N_LIFT] if r.lift_sensing_tracked else 0.0
    lift = ring[min(int(r.lift_delay_steps), ring.shape[0] - 1)]
    tgt = e.lift_target_m
    sn[S_LIFT] = lift
    sn[S_BEST_LIFT] = max(sn[S_BEST_LIFT], min(lift, tgt))
    # the sensed slip of this step (m), integrated as read: the noise averages out instead of piling up
    slip = slip_read * p.max_pull * p.agent_dt
    if tr >= e.lift_started_m:  # lifting began by the arm's encoder
        sn[S_LIFT_SLIP] += slip
    if lift >= tgt:
        sn[S_HOLD_TIME] += p.agent_dt
        sn[S_HOLD_SLIP] += slip
    else:
        sn[S_HOLD_TIME] = 0.0
        sn[S_HOLD_SLIP] = 0.0
    sn[S_PEAK_PINCH] = max(sn[S_PEAK_PINCH], pinch_read)


@kernel
def true_slip_readings(p, jo, k):
    """Jaw k's slip speed (the arm's top speed) and the share of its contact nodes that slip, as they are."""
    return jo[k, J_SLIP_DIST] / p.agent_dt / p.max_pull, jo[k, J_SLIP] / max(jo[k, J_CONTACT], 1.0)


@kernel(inline="always")
def force_readings(p, jo, ts, b, k, fresh):
    """Jaw k's normal and tangential force readings (N): the truth ``jo`` with the sensor's noise and the episode's
    bias, low-pass filtered where ``force_filter_s`` is set (``fresh``: the filter starts at this reading)."""
    r = p.env.randomization
    noise = ts.noise[b, N_FORCE + k]
    normal = jo[J_NORMAL] + noise + ts.draws[b, D_BIAS + k]
    tt = math.sqrt(jo[J_TX] * jo[J_TX] + jo[J_TY] * jo[J_TY] + jo[J_TZ] * jo[J_TZ])
    if r.force_noise_vector:  # |T + n_t|: n_t's components along T and across it
        ta, tc = tt + ts.noise[b, N_ALONG + k], ts.noise[b, N_ACROSS + k]
        tangential = math.sqrt(ta * ta + tc * tc)
    else:
        tangential = tt + abs(noise)
    if r.force_filter_s > 0.0:  # first-order low-pass, started at the episode's first reading
        a = 1.0 - math.exp(-p.agent_dt / r.force_filter_s)  # (its weight per agent step)
        if fresh:
            ts.readings[b, k], ts.readings[b, 3 + k] = normal, tangential
        else:
            ts.readings[b, k] += a * (normal - ts.readings[b, k])
            ts.readings[b, 3 + k] += a * (tangential - ts.readings[b, 3 + k])
        normal, tangential = ts.readings[b, k], ts.readings[b, 3 + k]
    return normal, tangential


@kernel(inline="always")
def observe_jaws(p, out, ts, b, fresh, o):
    """The per-jaw entries of env b's frame ``o`` (forces, contact, slip, friction use); returns the sum of the
    normal-force readings (N) and the mean slip-speed reading (the arm's top speed)."""
    e = p.env
    r = e.randomization
    ref = e.reference_force_N
    jo_all = out.jaw_out[b]
    pinch_read = 0.0
    slip_read = 0.0
    for k in range(3):
        jo = jo_all[k]
        normal, tangential = force_readings(p, jo, ts, b, k, fresh)
        pinch_read += normal
        o[I_NORMAL + k] = normal / ref
        o[I_TANGENTIAL + k] = tangential / ref
        o[I_CONTACT + k] = min(jo[J_CONTACT] / p.nominal[k], 2.0)
        speed, share = true_slip_readings(p, jo_all, k)
        if r.slip_sensing_exact:
            o[I_SLIP_SPEED + k] = speed + ts.noise[b, N_SLIP_SPEED + k]
            # incipient slip (what a tactile array sees): the share of the jaw's contact nodes that slip
            o[I_SLIPPING + k] = share
            if e.sensed_task_state:  # (v2: the tactile array's share is noisy too, and stays a share)
                o[I_SLIPPING + k] = min(max(share + ts.noise[b, N_SLIPPING + k], 0.0), 1.0)
        elif r.slip_sensing_binary:  # a slip detector: slipping or not
            o[I_SLIP_SPEED + k] = 1.0 if jo[J_SLIP_DIST] > 0.0 else 0.0
            o[I_SLIPPING + k] = 1.0 if jo[J_SLIP] > 0.0 else 0.0
        else:
            o[I_SLIP_SPEED + k] = 0.0
            o[I_SLIPPING + k] = 0.0
        slip_read += o[I_SLIP_SPEED + k] / 3.0
        # friction utilisation |T| / N (<= mu while the jaw sticks); 0.05 N keeps it finite off contact
        o[I_FRICTION_USE + k] = o[I_TANGENTIAL + k] / max(o[I_NORMAL + k], 0.05 / ref)
    return pinch_read, slip_read


@kernel(inline="always")
def observe_task_state(p, ts, b, fresh, o, tr, pinch_read, slip_read):
    """The task-state entries of env b's frame ``o`` (lift, hold, slips, lag, peak pinch, best lift): the truth (v0,
    v1) or, with ``sensed_task_state`` (v2), the sensed values (``tr``: the arm encoder's travel, m)."""
    e = p.env
    tgt = e.lift_target_m
    hold_tol = e.hold_slip_tolerance_m
    lift, best, hold, hold_slip, lift_slip, peak = (ts.lift[b], ts.best_lift[b], ts.hold_progress[b], ts.hold_slip[b],
                                                    ts.lift_slip[b], ts.peak_pinch[b])
    lag = tr - lift
    if e.sensed_task_state:
        sense_task_state(p, ts, b, fresh, pinch_read, slip_read, tr, ts.lift[b])
        sn = ts.sensed[b]
        lift, best, hold_slip, lift_slip, peak = (sn[S_LIFT], sn[S_BEST_LIFT], sn[S_HOLD_SLIP], sn[S_LIFT_SLIP],
                                                  sn[S_PEAK_PINCH])
        hold = min(sn[S_HOLD_TIME] / e.hold_time_s, 1.0) if e.hold_time_s > 0 else (1.0 if lift >= tgt else 0.0)
        # (no tracker: the lag, like every entry derived from it, is constant)
        lag = tr - lift if e.randomization.lift_sensing_tracked else 0.0
    o[I_LIFT] = lift / tgt
    o[I_HOLD] = hold
    o[I_HOLD_SLIP] = hold_slip / hold_tol if hold_tol > 0 else 0.0
    # grasper travel minus tissue lift: how far the tissue has slid out of (or lags) the jaws
    o[I_LIFT_LAG] = lag / tgt
    o[I_PEAK_PINCH] = peak / e.reference_force_N
    o[I_BEST_LIFT] = best / tgt
    o[I_LIFT_SLIP] = lift_slip / e.lift_slip_tolerance_m


@kernel(inline="always")
def observe_privileged(p, s, out, ts, b, o, tr):
    """The privileged entries of env b's frame ``o`` (``privileged_obs``): mu, the scales, the node displacements,
    with ``sensed_task_state`` the truth behind the sensed entries (PRIVILEGED_TRUTH), with
    ``privileged_perturbations`` the declared perturbations' entries."""
    e = p.env
    tgt = e.lift_target_m
    hold_tol = e.hold_slip_tolerance_m
    o[N_OBS] = ts.mu[b]
    o[N_OBS + 1] = s.kscale[b]
    o[N_OBS + 2] = s.mscale[b]
    for q in range(p.priv_nodes.shape[0]):
        i = p.priv_nodes[q]
        for c in range(3):
            o[N_OBS + 3 + 3 * q + c] = (s.x[b, i, c] - p.x_start[i, c]) / tgt
    j = N_OBS + 3 + 3 * p.priv_nodes.shape[0]
    if e.sensed_task_state:  # PRIVILEGED_TRUTH
        o[j] = ts.lift[b] / tgt
        o[j + 1] = ts.hold_progress[b]
        o[j + 2] = ts.hold_slip[b] / hold_tol if hold_tol > 0 else 0.0
        o[j + 3] = (tr - ts.lift[b]) / tgt
        o[j + 4] = ts.peak_pinch[b] / e.reference_force_N
        o[j + 5] = ts.best_lift[b] / tgt
        o[j + 6] = ts.lift_slip[b] / e.lift_slip_tolerance_m
        for k in range(3):
            speed, share = true_slip_readings(p, out.jaw_out[b], k)
            o[j + 7 + k] = speed
            o[j + 10 + k] = share
        j += N_PRIVILEGED_TRUTH
    if e.privileged_perturbations:  # the declared perturbations' privileged entries
        d = ts.draws[b]
        for q in range(p.priv_col.shape[0]):
            o[j + q] = (d[p.priv_col[q]] - p.priv_centre[q]) / p.priv_scale[q]


@kernel
def observe(p, s, out, ts, b):
    """Write env b's current frame (sensor noise ``ts.noise[b]``) into its history and observation; at a reset
    (the episode's step 0) the whole history is the current frame and the sensors' filters start from it.

    Every entry is what a named sensor gives (:data:`.sensors.SENSORS`); with ``sensed_task_state`` (v2) the task-state
    entries (lift, hold, slips, lag, peak pinch, best lift) come from the sensed values too, and the truth behind them
    goes to the privileged block (PRIVILEGED_TRUTH); without it (v0, v1) they are the simulation's truth."""
    e = p.env
    h = e.obs_history
    fd = p.frame_dim
    # (from the state, not an argument: a literal True / False would compile this function twice)
    fresh = ts.steps[b] == 0
    if not fresh:  # drop the oldest frame
        for k in range(h - 1):
            for c in range(fd):
                ts.frames[b, k, c] = ts.frames[b, k + 1, c]
    o = ts.frames[b, h - 1]
    rmin = s.g_rmin[b]
    o[I_OPENING] = (s.g_radius[b] - rmin) / (p.clear_radius - rmin)
    o[I_JAW_SPEED] = -s.g_vradius[b] / p.max_close
    tr = travel(p, s, ts, b)
    o[I_TRAVEL] = tr / e.lift_target_m
    o[I_PULL_SPEED] = (s.g_vpull[b, 0] * p.pull_dir[0] + s.g_vpull[b, 1] * p.pull_dir[1]
                       + s.g_vpull[b, 2] * p.pull_dir[2]) / p.max_pull
    pinch_read, slip_read = observe_jaws(p, out, ts, b, fresh, o)
    o[I_PREV_ACTION] = ts.prev_action[b, 0]
    o[I_PREV_ACTION + 1] = ts.prev_action[b, 1]
    o[I_TIME] = ts.steps[b] * p.agent_dt / e.time_limit_s
    observe_task_state(p, ts, b, fresh, o, tr, pinch_read, slip_read)
    if e.privileged_obs:
        observe_privileged(p, s, out, ts, b, o, tr)
    if fresh:
        for k in range(h - 1):
            for c in range(fd):
                ts.frames[b, k, c] = o[c]
    for k in range(h):
        for c in range(fd):
            ts.obs[b, k * fd + c] = ts.frames[b, k, c]


# ------------------------------------------------------------------------------------------------
# the reward: one small function per term (REWARD_TERMS), of the step's quantities and the reward record ``w``
# ------------------------------------------------------------------------------------------------


@kernel
def peak_force_weight(w, mu):
    """The friction weighting of the peak-force charge at friction ``mu``: mu / peak_force_mu_ref (1 when unset)."""
    return pinned(mu / w.peak_force_mu_ref, 1.0)  # (NaN reference: unset)


@kernel(inline="always")
def progress_term(w, progress):
    """Pays for the highest lift reached (a fraction of the target), once."""
    return w.progress * progress


@kernel(inline="always")
def hold_term(w, hold_gain):
    """Pays for the hold's progress (a fraction of hold_time_s)."""
    return w.hold * hold_gain


@kernel(inline="always")
def grasp_term(w, grip_gain):
    """Pays for the grip's rise up to grasp_force_N (a fraction of it)."""
    return w.grasp * grip_gain


@kernel(inline="always")
def slip_term(w, slip_m):
    """Charges this step's slip (m, mean over the jaws) per mm."""
    return -w.slip_per_mm * slip_m * 1e3


@kernel(inline="always")
def force_term(w, e, pinch_N, dt):
    """Charges the pinch held over the step (N / reference_force_N, per s)."""
    return -w.force_per_s * (pinch_N / e.reference_force_N) * dt


@kernel(inline="always")
def peak_force_term(w, e, peak_N, rise_N, weight, success, unsuccessful):
    """Charges the episode's peak pinch (``peak_N``; ``rise_N`` this step's rise of it), friction-weighted
    (``weight``): at success, or as made (each rise when it is made, refunded if the episode fails); with a knee
    (``peak_force_knee``) the charge's rise."""
    ref = e.reference_force_N
    if math.isnan(w.peak_force_knee):
        if w.peak_force_timing_as_made:  # charged as made, refunded without success
            charge = rise_N - (peak_N if unsuccessful else 0.0)
        else:
            charge = peak_N if success else 0.0
        return -(w.peak_force * (charge * weight) / ref)
    now = peak_charge_points(w, ref, peak_N, weight)
    if w.peak_force_timing_as_made:
        charge = now - peak_charge_points(w, ref, peak_N - rise_N, weight)
        charge -= now if unsuccessful else 0.0
    else:
        charge = now if success else 0.0
    return -charge


@kernel(inline="always")
def setpoint_change_term(w, e, ts, b):
    """Charges the pinch set-point's move since the last step of this episode (N; force set-points only)."""
    moved = 0.0
    if e.jaw_action_force and ts.steps[b] > 1:
        moved = abs(pinch_setpoint(e, ts.act[b, 0]) - pinch_setpoint(e, ts.prev_action[b, 0]))
    return -w.setpoint_change * moved


@kernel(inline="always")
def damage_term(w, damaged):
    """Charges a step whose peak contact pressure is above damage_stress_pa."""
    return -w.damage * (1.0 if damaged else 0.0)


@kernel(inline="always")
def success_term(w, success):
    """Pays the success bonus."""
    return w.success_bonus * (1.0 if success else 0.0)


@kernel(inline="always")
def failure_term(w, unsuccessful):
    """Charges every episode that ends without success, running out of time (never touching the tissue) included:
    not touching is then no safe haven."""
    return -w.failure_penalty * (1.0 if unsuccessful else 0.0)


@kernel(inline="always")
def reward_terms(p, ts, b, progress, hold_gain, grip_gain, slip, pinch, peak_rise, damaged, success, unsuccessful):
    """Every term of env b's reward this step into ``ts.terms[b]`` (REWARD_TERMS); returns their sum."""
    e = p.env
    w = e.reward
    t = ts.terms[b]
    t[R_PROGRESS] = progress_term(w, progress)
    t[R_HOLD] = hold_term(w, hold_gain)
    t[R_GRASP] = grasp_term(w, grip_gain)
    t[R_SLIP] = slip_term(w, slip)
    t[R_FORCE] = force_term(w, e, pinch, p.agent_dt)
    t[R_PEAK_FORCE] = peak_force_term(w, e, ts.peak_pinch[b], peak_rise, peak_force_weight(w, ts.mu[b]), success,
                                      unsuccessful)
    t[R_SETPOINT_CHANGE] = setpoint_change_term(w, e, ts, b)
    t[R_DAMAGE] = damage_term(w, damaged)
    t[R_SUCCESS] = success_term(w, success)
    t[R_FAILURE] = failure_term(w, unsuccessful)
    reward = 0.0
    for k in range(t.shape[0]):
        reward += t[k]
    return reward


# ------------------------------------------------------------------------------------------------
# the step after the physics: what the episode tracks, how it ends, the reward, the outputs
# ------------------------------------------------------------------------------------------------


@kernel(inline="always")
def track_lift_and_grip(p, s, ts, b, pinch, stress):
    """Env b's lift, best lift, grip and peaks after this step; returns (progress: the best lift's rise / target,
    grip_gain: the grip's rise, peak_rise: the peak pinch's rise, N)."""
    lift_new = 0.0
    for c in range(3):
        lift_new += (region_mean(p, s.x, b, c) - ts.region0[b, c]) * p.pull_dir[c]
    tgt = p.env.lift_target_m
    # progress pays for the highest lift reached (capped at the target), once: a lift that slips back is
    # not charged again, so an attempt that fails late still beats never touching the tissue
    best = max(ts.best_lift[b], min(lift_new, tgt))
    progress = (best - ts.best_lift[b]) / tgt
    ts.best_lift[b] = best
    ts.lift[b] = lift_new
    grip = min(pinch / p.env.reward.grasp_force_N, 1.0)
    grip_gain = grip - ts.grip[b]
    ts.grip[b] = grip
    peak_rise = max(pinch - ts.peak_pinch[b], 0.0)
    ts.peak_pinch[b] = max(ts.peak_pinch[b], pinch)
    ts.peak_stress[b] = max(ts.peak_stress[b], stress)
    return progress, grip_gain, peak_rise


@kernel(inline="always")
def track_slip_and_hold(p, ts, b, slip):
    """Env b's slip totals and hold after this step (``slip``: the step's slip, m); returns the hold's progress gain."""
    e = p.env
    dt = p.agent_dt
    lift_new = ts.lift[b]
    ts.slip_total[b] += slip
    if lift_new >= e.lift_started_m:
        ts.lift_started[b] = True
    if ts.lift_started[b]:
        ts.lift_slip[b] += slip
    at_target = lift_new >= e.lift_target_m
    if at_target and math.isnan(ts.time_to_lift[b]):
        ts.time_to_lift[b] = ts.steps[b] * dt
    if at_target:
        ts.hold_time[b] += dt
        ts.hold_slip[b] += slip
    else:
        ts.hold_time[b] = 0.0
        ts.hold_slip[b] = 0.0
    if ts.hold_slip[b] > e.hold_slip_tolerance_m:  # a hold spoilt by slip starts over (the timer restarts)
        ts.hold_time[b] = 0.0
        ts.hold_slip[b] = 0.0
    hold_new = min(ts.hold_time[b] / e.hold_time_s, 1.0) if e.hold_time_s > 0 else (1.0 if at_target else 0.0)
    hold_gain = hold_new - ts.hold_progress[b]
    ts.hold_progress[b] = hold_new
    return hold_gain


@kernel(inline="always")
def episode_end(p, ts, b, contact, stress, finite, volume_ratio):
    """How env b's episode stands after this step: (success, lost, slipped, damaged, failed, terminated,
    truncated). Success: at the lift target, held hold_time_s, no more slip since lifting began than
    lift_slip_tolerance_m; lost: no contact after lifting began; failed: a non-finite state or an inverted tet."""
    e = p.env
    slipped = ts.lift_slip[b] > e.lift_slip_tolerance_m
    at_target = ts.lift[b] >= e.lift_target_m
    success = at_target and ts.hold_time[b] >= e.hold_time_s - 1e-9 and not slipped
    lost = ts.lift_started[b] and contact == 0
    damaged = stress > e.damage_stress_pa
    # an inverted tet's springs and barrier push the wrong way
    failed = not (finite and (volume_ratio > 0.0 or not e.inverted_tet_is_failure))
    terminated = success or lost or failed or (damaged and e.terminate_on_damage)
    truncated = (not terminated) and ts.steps[b] >= p.max_steps
    return success, lost, slipped, damaged, failed, terminated, truncated


@kernel(inline="always")
def zero_observation(ts, b):
    """Env b's observation history and observation all zeros (a blown-up tissue: never hand out NaN)."""
    for k in range(ts.frames.shape[1]):
        for c in range(ts.frames.shape[2]):
            ts.frames[b, k, c] = 0.0
    for c in range(ts.obs.shape[1]):
        ts.obs[b, c] = 0.0


@kernel
def update(p, s, out, ts, b, finite, volume_ratio):
    """One agent step of env b after the physics: lift, slip, hold, reward terms, flags, observation and
    the episode's totals. ``finite``: the state is finite; ``volume_ratio``: its smallest tet volume ratio."""
    ts.steps[b] += 1
    jo = out.jaw_out[b]
    slip = (jo[0, J_SLIP_DIST] + jo[1, J_SLIP_DIST] + jo[2, J_SLIP_DIST]) / 3.0  # this step's slip, mean over jaws, m
    pinch = jo[0, J_NORMAL] + jo[1, J_NORMAL] + jo[2, J_NORMAL]
    stress = max(max(jo[0, J_PEAK_PRESSURE], jo[1, J_PEAK_PRESSURE]), jo[2, J_PEAK_PRESSURE])
    contact = jo[0, J_CONTACT] + jo[1, J_CONTACT] + jo[2, J_CONTACT]
    progress, grip_gain, peak_rise = track_lift_and_grip(p, s, ts, b, pinch, stress)
    hold_gain = track_slip_and_hold(p, ts, b, slip)
    success, lost, slipped, damaged, failed, terminated, truncated = episode_end(p, ts, b, contact, stress, finite,
                                                                                  volume_ratio)
    unsuccessful = (terminated or truncated) and not success
    reward = reward_terms(p, ts, b, progress, hold_gain, grip_gain, slip, pinch, peak_rise, damaged, success,
                          unsuccessful)
    if failed:  # a blown-up tissue: never hand out NaN observations or rewards
        reward = -p.env.reward.failure_penalty
        for k in range(ts.terms.shape[1]):
            if not math.isfinite(ts.terms[b, k]):
                ts.terms[b, k] = 0.0
        ts.lift[b] = 0.0
        ts.grip[b] = 0.0
    ts.reward[b] = reward
    ts.prev_action[b, 0] = ts.act[b, 0]
    ts.prev_action[b, 1] = ts.act[b, 1]
    observe(p, s, out, ts, b)
    if failed:
        zero_observation(ts, b)
    ts.pinch[b] = pinch
    ts.stress[b] = stress
    ts.contact[b] = contact
    ts.is_success[b] = success
    ts.lost_grasp[b] = lost
    ts.slipped[b] = slipped and not lost
    ts.damaged[b] = damaged
    ts.numerical_failure[b] = failed
    ts.min_volume_ratio[b] = volume_ratio
    ts.terminated[b] = terminated
    ts.truncated[b] = truncated
    done = terminated or truncated
    ts.done[b] = done
    # (an episode's first step starts the sum: a same-step reset must leave an ended episode's return)
    ts.episode_return[b] = reward if ts.steps[b] == 1 else ts.episode_return[b] + reward
    if done:
        ts.episode_length[b] = ts.steps[b]
        ts.episode_peak_pinch[b] = ts.peak_pinch[b]
        ts.episode_slip[b] = ts.slip_total[b]
        for c in range(ts.obs.shape[1]):
            ts.terminal_obs[b, c] = ts.obs[b, c]


@kernel
def restore_settled(p, s, out, b, first, stride):
    """Env b's tissue back to the settled state at rest (nodes and springs ``first``, ``first + stride``, ...:
    a GPU block shares them out among its threads)."""
    for i in range(first, s.x.shape[1], stride):
        for c in range(3):
            s.x[b, i, c] = p.x_start[i, c]
            s.v[b, i, c] = 0.0
            s.f_ext[b, i, c] = 0.0
            out.contact_force[b, i, c] = 0.0
        out.contact_state[b, i] = 0
        s.held[b, i] = 0
    for e in range(first, s.fv.shape[1], stride):
        s.fv[b, e] = p.fv_start[e]
        s.dl_prev[b, e] = p.dl_start[e]


@kernel
def draw_episode(p, ts, b):
    """Turn env b's raw variates in ``ts.draws[b]`` into the episode's draws in place, each column by its law
    (:func:`draw_value`; the declarations of .perturbations): friction, scales, the pose's offset and turns, the
    robustness axes' levels and the force-noise level."""
    d = ts.draws[b]
    for k in range(d.shape[0]):
        d[k] = draw_value(p.draw_law[k], p.draw_a[k], p.draw_b[k], d[k])


@kernel
def begin_episode(p, s, out, ts, b):
    """Start env b's episode from its draws and pins (after :func:`restore_settled`):
    friction, scales and the perturbed pose, open jaws at rest, cleared episode state, the first frame."""
    e = p.env
    r = e.randomization
    d = ts.draws[b]
    pin = ts.pin[b]
    mu = pinned(pin[P_MU], d[D_MU])
    ts.mu[b] = mu
    s.mu_s[b] = mu
    s.mu_k[b] = pinned(pin[P_MU_KINETIC], mu)
    s.kscale[b] = pinned(pin[P_KS], d[D_KS])
    s.mscale[b] = pinned(pin[P_MS], d[D_MS])
    deg = math.pi / 180.0
    perturb_pose(p.pose_tip, p.pose_axis, p.pose_e1, d, pinned(pin[P_OFFSET], r.pose_offset_m),
                 pinned(pin[P_TILT], r.pose_tilt_deg) * deg, pinned(pin[P_AZIMUTH], r.pose_azimuth_deg) * deg,
                 s.g_tip[b], s.g_axis[b], s.g_e1[b])
    for c in range(3):  # the pose's error from the planned one (the placement's derived columns)
        d[D_TIP_OFFSET + c] = s.g_tip[b, c] - p.pose_tip[c]
        d[D_AXIS_CHANGE + c] = s.g_axis[b, c] - p.pose_axis[c]
        d[D_E1_CHANGE + c] = s.g_e1[b, c] - p.pose_e1[c]
    s.t[b] = 0.0
    # the jaws open just clear of the tissue at this episode's own pose, by the rule that sets the planned pose's
    # start radius. Not as wide as the largest placement error in the ranges needs: a 5 mm range then opened
    # every episode 4 mm wider, and a policy that pulls while it closes never reached the tissue.
    s.g_radius[b] = jaw_start_radius(
        jaw_reach(s.x[b], p.surface, (s.g_tip[b, 0], s.g_tip[b, 1], s.g_tip[b, 2]),
                  (s.g_axis[b, 0], s.g_axis[b, 1], s.g_axis[b, 2]), (s.g_e1[b, 0], s.g_e1[b, 1], s.g_e1[b, 2]),
                  p.jaw_length, p.jaw_half_width), p.open_radius)
    s.g_vradius[b] = 0.0
    for c in range(3):
        s.g_vpull[b, c] = 0.0
        out.anchor_out[b, c] = 0.0
        for col in range(out.jaw_out.shape[2]):
            out.jaw_out[b, c, col] = 0.0
        ts.tip0[b, c] = s.g_tip[b, c]
        ts.region0[b, c] = region_mean(p, s.x, b, c)
        for col in range(c, N_NOISE, 3):  # (no sensor noise in the first frame)
            ts.noise[b, col] = 0.0
    s.g_force[b, G_PINCH] = 0.0
    s.g_force[b, G_SETPOINT] = -1.0  # (the force loop off: the closing speed is commanded)
    if e.jaw_action_force:  # the jaw motor starts in force control at zero force (jaws at rest)
        s.g_force[b, G_SETPOINT] = 0.0
        s.g_force[b, G_GAIN] = e.force_loop_gain_m_s_per_N * d[D_GAIN]
        s.g_force[b, G_VMAX] = p.max_close
    rest0, rest1 = rest_action(e)
    for k in range(ts.queue.shape[1]):  # until the first action arrives the grasper rests
        ts.queue[b, k, 0] = rest0
        ts.queue[b, k, 1] = rest1
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
    ts.time_to_lift[b] = math.nan
    ts.hold_progress[b] = 0.0
    ts.travel_target[b] = 0.0
    observe(p, s, out, ts, b)


# ------------------------------------------------------------------------------------------------
# the CPU core's loops over its envs (here, not in core.py: numba checks a cached function against its own
# file only, and these compile the functions above into themselves)
# ------------------------------------------------------------------------------------------------


@kernel
def command_batch(p, s, ts, actions):
    """Every env's action (B,2) -> its commands."""
    for b in range(actions.shape[0]):
        command(p, s, ts, b, actions[b, 0], actions[b, 1])


@kernel
def update_batch(p, s, out, ts, finite, volume_ratio):
    """Every env's step after the physics."""
    for b in range(finite.shape[0]):
        update(p, s, out, ts, b, finite[b], volume_ratio[b])


@kernel
def start_episode(p, s, out, ts, b):
    """Env b's new episode from its draws (already turned into values) and pins: the settled tissue, then
    :func:`begin_episode`."""
    restore_settled(p, s, out, b, 0, 1)
    begin_episode(p, s, out, ts, b)
