"""Headless rerun recordings of GraspLift episodes (``.rrd`` files, no viewer, no network).

:class:`RerunRecorder` wraps a single :class:`~msdgrasp.envs.grasp_lift.GraspLiftEnv` (bare or from
``gym.make``) and logs every agent step to a rerun file sink. :func:`record_episode` runs one episode
with a policy and returns a summary. Open a recording with ``msdgrasp replay FILE`` or ``rerun FILE``.

Layout of a recording
---------------------
One recording (application id ``msdgrasp``) per file. Every episode lives under its own entity prefix
``episode_KKKK`` (K = the episode's index since the recorder was created, zero-padded), and every
episode's clocks start at 0, so episodes never overwrite each other and their time series can be
overlaid:

=======================================  ====================================================
entity                                   content
=======================================  ====================================================
``episode_K/world/tissue``               Mesh3D of the tissue surface: triangles (static, logged
                                         once), per step vertex positions, normals and colours
                                         (nodal normal stress, or contact pressure; blue =
                                         tension, white = 0, red = compression at the colour
                                         range, by default the damage threshold)
``episode_K/world/grasper/jaws``         Mesh3D of the three jaw faces (+ ``outline``, ``shaft``)
``episode_K/world/anchors``              Points3D of the anchored nodes
``episode_K/world/contacts``             Arrows3D: contact force on the tissue at each contact
                                         node, head on the node, green = stick, red = slip
``episode_K/forces/{normal,tangential}/jaw_J``   per-jaw forces, N
``episode_K/forces/pinch``               ``info["pinch_force_N"]``
``episode_K/grasp/{lift_m,slip_distance_m,jaw_radius_m}``   ``info`` lift, slip and jaw radius, m
``episode_K/stress/peak_pa``             ``info["peak_stress_pa"]`` (+ ``damage_threshold_pa``)
``episode_K/contact/{stick,slip}_nodes`` contact node counts
``episode_K/reward/{term,total,return}`` each ``info["reward_terms"]`` entry, the reward, its sum
``episode_K/action/{close,pull}``        the action applied
``episode_K/log``                        TextLog: domain draws at reset, outcome at the end
=======================================  ====================================================

Timelines: ``sim_time`` (simulated seconds, a duration timeline) and ``step`` (agent steps; the reset
frame is step 0, the state after the n-th action is step n). The wall-clock ``log_time``/``log_tick``
timelines are switched off. A default blueprint is stored in the file: one tab per episode (3D view,
forces, grasp, reward/stress/contact/action plots) and, with several episodes, a tab overlaying the
pinch force and lift of all episodes.

Files and failures
------------------
Data goes to a temp file ``.NAME.XXXX.part`` next to the destination, which is fsync'ed, checked with
rerun's own reader and renamed onto the destination only when complete: on :meth:`RerunRecorder.close`
(one file for all episodes) or at the end of each episode when the path contains ``{episode}``
(``runs/ep_{episode:03d}.rrd``: one file per episode). The destination therefore never holds a partial
recording; it either does not exist yet or holds the previous complete one.

The destination is checked at construction (folder created if missing, a temp file created in it): an
unusable path raises :class:`RecordingError` (an ``OSError``) naming it. Later failures (disk full,
folder removed, rerun errors) raise :class:`RecordingError` with ``on_error="raise"`` (default); with
``on_error="warn"`` they issue a :class:`RecordingWarning`, drop the broken recording (temp file
removed, destination untouched) and let the wrapped env run on, so a training run never dies because of
its recorder.
"""

from __future__ import annotations

import atexit
import functools
import os
import warnings
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from ..physics.config import require_extra
from .rrd_file import RecordingError, RecordingWarning, RrdSink, check_destination, recording_error

__all__ = ["RecordingError", "RecordingWarning", "RerunRecorder", "record_episode", "stress_colors"]

TIMELINE_TIME = "sim_time"
TIMELINE_STEP = "step"

#: frames of scalar rows buffered before they are sent as columns (also sent at each episode end)
SCALAR_FLUSH_FRAMES = 64

JAW_COLORS = np.array([[255, 160, 40, 255], [170, 90, 230, 255], [40, 190, 230, 255]], dtype=np.uint8)
STICK_COLOR = (40, 200, 60, 255)
SLIP_COLOR = (230, 40, 40, 255)
ANCHOR_COLOR = (250, 220, 40, 255)


# ------------------------------------------------------------------------------------------------
# colour map
# ------------------------------------------------------------------------------------------------


def stress_colors(values: np.ndarray, vmax: float, signed: bool = True) -> np.ndarray:
    """(n,4) uint8 RGBA of ``values`` on a diverging map: -vmax blue, 0 white, +vmax red (clipped).

    With ``signed=False`` the values are clipped at 0 (white) and only the red half is used.
    """
    v = np.asarray(values, dtype=np.float64) / float(vmax)
    v = np.clip(np.nan_to_num(v, nan=0.0), -1.0 if signed else 0.0, 1.0)
    white = np.array([245.0, 245.0, 240.0])
    red = np.array([200.0, 20.0, 30.0])
    blue = np.array([30.0, 70.0, 200.0])
    a = np.abs(v)[:, None]
    end = np.where((v >= 0)[:, None], red, blue)
    rgb = white * (1.0 - a) + end * a
    out = np.empty((len(v), 4), dtype=np.uint8)
    out[:, :3] = np.round(rgb).astype(np.uint8)
    out[:, 3] = 255
    return out


def _finish_at_exit(ref: weakref.ReferenceType) -> None:
    rec = ref()
    if rec is not None:
        try:
            rec.finish()
        except Exception as exc:  # noqa: BLE001 - never raise at interpreter exit
            warnings.warn(f"rerun recording not finished at exit: {exc}", RecordingWarning, stacklevel=1)


# ------------------------------------------------------------------------------------------------
# the wrapper
# ------------------------------------------------------------------------------------------------


class RerunRecorder(gym.Wrapper):
    """Record GraspLift episodes to a rerun ``.rrd`` file, headlessly (see the module docstring).

    Parameters
    ----------
    env : a single GraspLift env (``GraspLiftEnv``, ``GraspLiftSphereEnv`` or ``gym.make`` of them)
    path : destination ``.rrd``. With ``{episode}`` in it (``"runs/ep_{episode:03d}.rrd"``) every
        recorded episode gets its own file, finished at the episode's end; otherwise all episodes go to
        one file, finished by :meth:`close` / :meth:`finish`.
    on_error : ``"raise"`` (default) or ``"warn"`` (warn, drop the broken recording, keep running).
        Applies at construction too: with ``"warn"`` an unusable path leaves a pass-through wrapper.
    episode_trigger : ``f(episode_index) -> bool``, which episodes to record (default: all).
    color_by : ``"stress"`` (nodal normal stress of the surface, the paper's Fig. 8 quantity, signed) or
        ``"contact_pressure"`` (normal contact force / node area, >= 0).
    color_range_pa : stress giving full red (blue); default the env's ``damage_stress_pa``.
    force_scale_m_per_N : length of the contact-force arrows per newton.
    blueprint : store a default viewer layout in the file.
    name : recording name shown in the viewer (default: the file name).
    """

    def __init__(
        self,
        env: gym.Env,
        path: str | os.PathLike,
        *,
        on_error: str = "raise",
        episode_trigger: Callable[[int], bool] | None = None,
        color_by: str = "stress",
        color_range_pa: float | None = None,
        force_scale_m_per_N: float = 0.02,
        blueprint: bool = True,
        name: str | None = None,
    ) -> None:
        super().__init__(env)
        # a missing rerun is an error here, never a recording dropped with on_error="warn"
        require_extra("viz", "RerunRecorder", "rerun")
        if on_error not in ("raise", "warn"):
            raise ValueError(f"on_error must be 'raise' or 'warn', got {on_error!r}")
        if color_by not in ("stress", "contact_pressure"):
            raise ValueError(f"color_by must be 'stress' or 'contact_pressure', got {color_by!r}")
        core = getattr(env.unwrapped, "core", None)
        if core is None or not hasattr(core, "sim") or getattr(core, "num_envs", None) != 1:
            raise TypeError("RerunRecorder wraps a single GraspLift env (one tissue); got "
                            + type(env.unwrapped).__name__)
        self.core = core
        self.on_error = on_error
        self.episode_trigger = episode_trigger
        self.color_by = color_by
        cfg = core.config
        self.color_range_pa = float(color_range_pa if color_range_pa is not None else cfg.damage_stress_pa)
        if not np.isfinite(self.color_range_pa) or self.color_range_pa <= 0:
            raise ValueError(f"color_range_pa must be a positive number, got {color_range_pa!r}")
        self.force_scale = float(force_scale_m_per_N)
        self.use_blueprint = bool(blueprint)
        self.errors: list[str] = []
        self.paths: list[Path] = []  # finished files, in order

        raw = os.fspath(path)
        self.per_episode = "{episode" in raw
        if self.per_episode:
            try:
                probe = Path(raw.format(episode=0))
            except (KeyError, IndexError, ValueError) as exc:
                raise ValueError(f"path template {raw!r}: only the field {{episode}} is allowed ({exc})") from None
        else:
            probe = Path(raw)
        self._template = raw
        self.path = probe  # single-file mode: the destination; per-episode mode: episode 0's
        self._name = name

        # static geometry
        scene = core.scene
        mesh = scene.mesh
        self._surf = np.asarray(mesh.surface_nodes, dtype=np.int64)
        self._tris_local = np.searchsorted(self._surf, np.asarray(mesh.surface_tris)).astype(np.uint32)
        fixed = np.asarray(scene.model.fixed, dtype=bool)
        self._anchors = np.flatnonzero(fixed) if fixed.size else np.zeros(0, dtype=np.int64)
        self._jaw_tris = np.array([[4 * k, 4 * k + 1, 4 * k + 2] for k in range(3)]
                                  + [[4 * k, 4 * k + 2, 4 * k + 3] for k in range(3)], dtype=np.uint32)
        self._jaw_vcolors = np.repeat(JAW_COLORS, 4, axis=0)

        self._sink: RrdSink | None = None
        self._disabled = False  # single-file mode after a failure (warn): nothing more is recorded
        self._episode = -1  # index of the current episode (counts every reset)
        self._prefix: str | None = None  # entity prefix of the episode being recorded, None if not recording
        self._return = 0.0
        self._closed = False
        self._scalars: dict[str, tuple[list[int], list[float], list[float]]] = {}
        self._frames_pending = 0

        try:
            if self.per_episode:
                check_destination(probe)
            else:
                self._sink = RrdSink(probe, name or probe.name)
        except RecordingError as exc:
            self._fail(exc, stage="opening")
        self._atexit = functools.partial(_finish_at_exit, weakref.ref(self))
        atexit.register(self._atexit)

    # -- gymnasium API ---------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._end_episode(outcome="reset before the episode ended")
        self._episode += 1
        if not self._closed and self._wanted(self._episode):
            self._guard(self._begin_episode, info, seed)
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self._prefix is not None:
            self._return += float(reward)
            self._guard(self._log_frame, info, float(reward), np.asarray(action, dtype=np.float64))
            if terminated or truncated:
                if info.get("is_success"):
                    outcome = "success"
                elif terminated:
                    why = [k for k in ("lost_grasp", "damaged", "numerical_failure") if info.get(k)]
                    outcome = "terminated" + (f": {', '.join(why)}" if why else "")
                else:
                    outcome = "truncated (time limit)"
                self._end_episode(outcome)
        return obs, reward, terminated, truncated, info

    def close(self):
        try:
            self.finish()
        finally:
            super().close()

    # -- recorder API ----------------------------------------------------------------------------
    def finish(self) -> list[Path]:
        """Finish and write the recording(s) without closing the env; returns the files written.

        Idempotent. In single-file mode the file is written if at least one episode was recorded
        (otherwise nothing is created); further steps are not recorded.
        """
        if self._closed:
            return list(self.paths)
        self._end_episode(outcome="recording closed")
        self._closed = True
        atexit.unregister(self._atexit)
        sink, self._sink = self._sink, None
        if sink is not None:
            if sink.episodes:
                self._guard(self._commit, sink)
            else:
                sink.discard()
        return list(self.paths)

    def abort(self) -> None:
        """Drop everything not yet written (temp files removed; finished files stay)."""
        self._prefix = None
        self._closed = True
        atexit.unregister(self._atexit)
        if self._sink is not None:
            self._sink.discard()
            self._sink = None

    @property
    def recording(self) -> bool:
        """True while an episode is being recorded."""
        return self._prefix is not None

    # -- internals -------------------------------------------------------------------------------
    def _wanted(self, episode: int) -> bool:
        if self._disabled:
            return False
        return self.episode_trigger is None or bool(self.episode_trigger(episode))

    def _fail(self, exc: BaseException, stage: str) -> None:
        if not isinstance(exc, RecordingError):
            where = self._sink.path if self._sink is not None else self.path
            exc = recording_error(f"recording {where} failed while {stage}", where, exc)
        # drop what is broken: the current episode (and, in single-file mode, the whole file)
        self._prefix = None
        self._scalars = {}
        self._frames_pending = 0
        if self._sink is not None:
            self._sink.discard()
            self._sink = None
        if not self.per_episode:
            self._disabled = True
        if self.on_error == "raise":
            raise exc
        self.errors.append(str(exc))
        warnings.warn(f"{exc} (recording dropped; the environment keeps running)", RecordingWarning, stacklevel=3)

    def _guard(self, fn, *args, stage: str | None = None) -> Any:
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001 - a recorder never crashes a run with on_error="warn"
            self._fail(exc, stage or fn.__name__.strip("_").replace("_", " "))
            return None

    def _commit(self, sink: RrdSink) -> None:
        bp = self._blueprint(sink.episodes) if self.use_blueprint else None
        self.paths.append(sink.commit(bp))

    def _begin_episode(self, info: dict[str, Any], seed: int | None) -> None:
        import rerun as rr

        k = self._episode
        if self.per_episode:
            path = Path(self._template.format(episode=k))
            self._sink = RrdSink(path, self._name or path.name)
        sink = self._sink
        if sink is None:
            return
        prefix = f"episode_{k:04d}"
        self._prefix = prefix
        self._return = 0.0
        sink.episodes.append(prefix)
        rec = sink.rec
        log = sink.log
        # static per episode: axes (z up, gravity -z), topology, colours of the jaws, series styles
        log(f"{prefix}/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log(f"{prefix}/world/tissue", rr.Mesh3D.from_fields(triangle_indices=self._tris_local), static=True)
        log(f"{prefix}/world/grasper/jaws",
                rr.Mesh3D.from_fields(triangle_indices=self._jaw_tris, vertex_colors=self._jaw_vcolors), static=True)
        for j in range(3):
            log(f"{prefix}/forces/normal/jaw_{j}",
                rr.SeriesLines(colors=JAW_COLORS[j], names=f"jaw {j} normal", widths=2.0), static=True)
            log(f"{prefix}/forces/tangential/jaw_{j}",
                rr.SeriesLines(colors=JAW_COLORS[j], names=f"jaw {j} tangential", widths=1.0), static=True)
        log(f"{prefix}/forces/pinch", rr.SeriesLines(colors=(20, 20, 20), names="pinch", widths=2.5), static=True)
        log(f"{prefix}/contact/stick_nodes", rr.SeriesLines(colors=STICK_COLOR, names="stick nodes"), static=True)
        log(f"{prefix}/contact/slip_nodes", rr.SeriesLines(colors=SLIP_COLOR, names="slip nodes"), static=True)
        log(f"{prefix}/stress/damage_threshold_pa",
                rr.SeriesLines(colors=(230, 40, 40), names="damage threshold", widths=1.0), static=True)
        draws = ", ".join(f"{key}={float(v):.4g}" for key, v in info.items()
                          if key in ("mu", "mu_kinetic", "stiffness_scale", "mass_scale"))
        self._set_time(rec)
        log(f"{prefix}/log", rr.TextLog(f"episode {k} reset (seed={seed}): {draws}", level="INFO"))
        self._log_frame(info, None, None)

    def _end_episode(self, outcome: str) -> None:
        if self._prefix is None:
            return
        import rerun as rr

        prefix, self._prefix = self._prefix, None
        sink = self._sink

        def _finish() -> None:
            self._flush_scalars()
            rec = sink.rec
            self._set_time(rec)
            sink.log(f"{prefix}/log", rr.TextLog(
                f"{prefix} ended after {int(self.core.steps[0])} steps: {outcome}; return {self._return:.4g}",
                level="INFO"))
            if self.per_episode:
                self._sink = None
                self._commit(sink)

        if sink is not None:
            self._guard(_finish, stage="finishing the episode")

    def _set_time(self, rec) -> None:
        rec.set_time(TIMELINE_STEP, sequence=int(self.core.steps[0]))
        rec.set_time(TIMELINE_TIME, duration=float(self.core.sim.t[0]))

    def _log_frame(self, info: dict[str, Any], reward: float | None, action: np.ndarray | None) -> None:
        """Log the current state of the first tissue (and the step's info/reward/action) at the current time."""
        import rerun as rr

        from ..physics.contact import J_CONTACT, J_NORMAL, J_SLIP, J_STICK, J_TX, J_TZ, SLIP, WALL_SLIP
        from ..physics.grasper import GrasperPose, jaw_face_corners
        from ..physics.stress import surface_normal_stress

        if self._prefix is None or self._sink is None:
            return
        p = self._prefix
        rec = self._sink.rec
        log = self._sink.log
        core = self.core
        sim = core.sim
        scene = core.scene
        mesh = scene.mesh
        self._set_time(rec)

        x = sim.x[0]
        surf = self._surf
        normals = mesh.vertex_normals(x)
        if self.color_by == "stress":
            value = surface_normal_stress(scene.model, x, float(sim.kscale[0]))[surf]
            colors = stress_colors(value, self.color_range_pa, signed=True)
        else:
            area = mesh.surface_vertex_areas(x)[surf]
            fn = -np.einsum("ij,ij->i", sim.contact_force[0, surf], normals[surf])
            value = np.where(area > 0, fn / np.where(area > 0, area, 1.0), 0.0)
            colors = stress_colors(value, self.color_range_pa, signed=False)
        log(f"{p}/world/tissue", rr.Mesh3D.from_fields(
            vertex_positions=x[surf].astype(np.float32), vertex_normals=normals[surf].astype(np.float32),
            vertex_colors=colors))

        pose = GrasperPose(sim.g_tip[0].copy(), sim.g_axis[0].copy(), sim.g_e1[0].copy())
        corners = jaw_face_corners(pose, float(sim.g_radius[0]), scene.grasper)  # (3,4,3)
        log(f"{p}/world/grasper/jaws",
            rr.Mesh3D.from_fields(vertex_positions=corners.reshape(12, 3).astype(np.float32)))
        loops = np.concatenate([corners, corners[:, :1]], axis=1)
        log(f"{p}/world/grasper/outline", rr.LineStrips3D(loops.astype(np.float32), colors=JAW_COLORS, radii=0.0003))
        back = pose.tip - scene.grasper.jaw_length_m * pose.axis
        log(f"{p}/world/grasper/shaft", rr.LineStrips3D(
            [np.stack([back, back - 0.08 * pose.axis]).astype(np.float32)], colors=(120, 120, 130), radii=0.002))
        if self._anchors.size:
            log(f"{p}/world/anchors",
                rr.Points3D(x[self._anchors].astype(np.float32), colors=ANCHOR_COLOR, radii=0.0012))

        state = sim.contact_state[0]
        idx = np.flatnonzero(state > 0)
        f = sim.contact_force[0, idx] * self.force_scale
        cols = np.where(np.isin(state[idx], (SLIP, WALL_SLIP))[:, None], np.array(SLIP_COLOR, np.uint8),
                        np.array(STICK_COLOR, np.uint8))
        log(f"{p}/world/contacts", rr.Arrows3D(
            origins=(x[idx] - f).astype(np.float32).reshape(-1, 3), vectors=f.astype(np.float32).reshape(-1, 3),
            colors=cols.reshape(-1, 4), radii=0.0003))

        # scalar series: buffered, sent as columns (one chunk per entity per flush)
        jo = sim.jaw_out[0]
        tang = np.linalg.norm(jo[:, J_TX : J_TZ + 1], axis=1)
        row = self._row
        for j in range(3):
            row(f"{p}/forces/normal/jaw_{j}", jo[j, J_NORMAL])
            row(f"{p}/forces/tangential/jaw_{j}", tang[j])
        row(f"{p}/forces/pinch", info.get("pinch_force_N", jo[:, J_NORMAL].sum()))
        row(f"{p}/grasp/lift_m", info.get("lifted_m", core.lift[0]))
        row(f"{p}/grasp/slip_distance_m", info.get("slip_distance_m", core.slip_total[0]))
        row(f"{p}/grasp/jaw_radius_m", sim.g_radius[0])
        row(f"{p}/stress/peak_pa", info.get("peak_stress_pa", 0.0))
        row(f"{p}/stress/damage_threshold_pa", core.config.damage_stress_pa)
        counts = jo[:, [J_CONTACT, J_STICK, J_SLIP]].sum(axis=0)
        row(f"{p}/contact/stick_nodes", counts[1])
        row(f"{p}/contact/slip_nodes", counts[2])
        if reward is not None:
            for term, v in (info.get("reward_terms") or {}).items():
                row(f"{p}/reward/{term}", v)
            row(f"{p}/reward/total", reward)
            row(f"{p}/reward/return", self._return)
        if action is not None:
            a = np.clip(action.reshape(-1), -1.0, 1.0)
            row(f"{p}/action/close", a[0])
            row(f"{p}/action/pull", a[1])
        self._frames_pending += 1
        if self._frames_pending >= SCALAR_FLUSH_FRAMES:
            self._flush_scalars()

    def _row(self, entity: str, value) -> None:
        steps, times, values = self._scalars.setdefault(entity, ([], [], []))
        steps.append(int(self.core.steps[0]))
        times.append(float(self.core.sim.t[0]))
        values.append(float(value))

    def _flush_scalars(self) -> None:
        """Send the buffered scalar rows of the current file as columns (``step`` and ``sim_time``)."""
        import rerun as rr

        pending, self._scalars = self._scalars, {}
        self._frames_pending = 0
        if self._sink is None:
            return
        rec = self._sink.rec
        for entity, (steps, times, values) in pending.items():
            rec.send_columns(
                entity,
                indexes=[rr.TimeColumn(TIMELINE_STEP, sequence=steps), rr.TimeColumn(TIMELINE_TIME, duration=times)],
                columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64)),
                strict=True,
            )

    def _blueprint(self, episodes: list[str]):
        import rerun.blueprint as rrb

        def tab(p: str):
            return rrb.Horizontal(
                rrb.Spatial3DView(origin=f"/{p}/world", name=f"{p} 3D"),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin=f"/{p}/forces", name="forces (N)"),
                    rrb.TimeSeriesView(origin=f"/{p}/grasp", name="lift, slip, jaw radius (m)"),
                    rrb.Tabs(
                        rrb.TimeSeriesView(origin=f"/{p}/reward", name="reward"),
                        rrb.TimeSeriesView(origin=f"/{p}/stress", name="peak stress (Pa)"),
                        rrb.TimeSeriesView(origin=f"/{p}/contact", name="contact nodes"),
                        rrb.TimeSeriesView(origin=f"/{p}/action", name="action"),
                    ),
                ),
                column_shares=[3, 2],
                name=p,
            )

        tabs = [tab(p) for p in episodes]
        if len(episodes) > 1:
            tabs.append(rrb.Vertical(
                rrb.TimeSeriesView(origin="/", contents=[f"/{p}/forces/pinch" for p in episodes],
                                   name="pinch force, all episodes (N)"),
                rrb.TimeSeriesView(origin="/", contents=[f"/{p}/grasp/lift_m" for p in episodes],
                                   name="lift, all episodes (m)"),
                name="all episodes",
            ))
        return rrb.Blueprint(rrb.Tabs(*tabs), rrb.TimePanel(timeline=TIMELINE_TIME), collapse_panels=False)


# ------------------------------------------------------------------------------------------------
# one episode
# ------------------------------------------------------------------------------------------------


def record_episode(
    env: gym.Env,
    policy_fn: Callable[[np.ndarray], Any],
    path: str | os.PathLike,
    seed: int | None = None,
    options: dict[str, Any] | None = None,
    max_steps: int | None = None,
    **recorder_kwargs: Any,
) -> dict[str, Any]:
    """Run one episode of ``env`` with ``action = policy_fn(obs)``, recorded to ``path``.

    The env is not closed. Returns ``{"return", "steps", "success", "terminated", "truncated", "path",
    "size_bytes", "lifted_m", "slip_distance_m", "peak_stress_pa"}``. On an exception (policy, env or
    recording) nothing is written and the exception propagates.
    """
    if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer))
                                  or max_steps < 1):
        raise ValueError(f"max_steps must be an integer >= 1 or None, got {max_steps!r}")
    if "{episode" in os.fspath(path):
        raise ValueError("record_episode writes one file: path must not contain {episode}")
    recorder = RerunRecorder(env, path, **recorder_kwargs)
    total = 0.0
    steps = 0
    terminated = truncated = False
    info: dict[str, Any] = {}
    try:
        obs, info = recorder.reset(seed=seed, options=options)
        while True:
            obs, reward, terminated, truncated, info = recorder.step(policy_fn(obs))
            total += float(reward)
            steps += 1
            if terminated or truncated or (max_steps is not None and steps >= max_steps):
                break
        written = recorder.finish()
    except BaseException:
        recorder.abort()
        raise
    out = written[0] if written else None
    return {
        "return": total,
        "steps": steps,
        "success": bool(info.get("is_success", False)),
        "terminated": bool(terminated),
        "truncated": bool(truncated),
        "path": None if out is None else str(out),
        "size_bytes": None if out is None else out.stat().st_size,
        "lifted_m": float(info.get("lifted_m", 0.0)),
        "slip_distance_m": float(info.get("slip_distance_m", 0.0)),
        "peak_stress_pa": float(info.get("peak_stress_pa", 0.0)),
    }
