"""Headless RGB rendering of a GraspLift sub-env (matplotlib Agg, no display, no pyplot state).

:func:`render_rgb` draws one frame of sub-env ``index`` of a :class:`GraspLiftCore` that explains the grasp:

* the deformed tissue surface, coloured by local **strain** (the largest stretch or compression of the
  springs at a node relative to the settled start, %: shows deformation under and around the jaws however
  far the organ has been lifted), by nodal **contact pressure** (kPa) or by **displacement** (mm), with a
  colour bar and its unit;
* the contact nodes, marked green where they stick and red where they slip;
* the three jaw faces and, per jaw, the normal (black) and friction (orange) force on the tissue as arrows
  (25 mm per N);
* an inset of pinch force (N) and lift (mm) against time, with the lift target;
* a title with mu, the time, the pinch force, the lift and the outcome so far.

The camera looks at the grasped end of the organ and the grasper (the anchored far end is cut off). One
matplotlib Figure per core and image size is built on the first call and cached on the core
(``core._render_cache``); later frames update the artists, so a frame costs one Agg draw (~50 ms at 640 x
480). Rendering runs only when asked (``render_mode="rgb_array"`` and ``env.render()``, ``msdgrasp record
--video``); :mod:`msdgrasp.envs.video` writes frames to mp4 or GIF.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..physics.config import needs_extra
from ..physics.contact import J_NORMAL, J_TX, J_TZ, SLIP, STICK, WALL_SLIP, WALL_STICK
from ..physics.grasper import GrasperPose, jaw_face_corners

#: full scale of each colour map: strain in %, contact pressure in kPa, displacement in mm
STRAIN_FULL_SCALE_PCT = 20.0
STRESS_FULL_SCALE_KPA = 60.0
DISP_FULL_SCALE_MM = 40.0
JAW_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd")
COLOR_BY = ("strain", "pressure", "displacement")
#: marker colours of sticking / slipping contact nodes (tests look for these pixels)
STICK_COLOUR = "#00e000"
SLIP_COLOUR = "#ff0000"
#: force arrows: metres of arrow per newton
ARROW_M_PER_N = 0.025
_COLOUR_LABELS = {"strain": ("strain (%)", STRAIN_FULL_SCALE_PCT),
                  "pressure": ("contact pressure (kPa)", STRESS_FULL_SCALE_KPA),
                  "displacement": ("displacement (mm)", DISP_FULL_SCALE_MM)}
_CMAPS = {"strain": "viridis", "pressure": "inferno", "displacement": "cividis"}


class _Frame:
    """The cached figure of one core and image size."""

    def __init__(self, core: Any, width: int, height: int) -> None:
        with needs_extra("viz", "rendering"):
            from matplotlib import colormaps
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure
            from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        dpi = 100
        self.width, self.height = width, height
        self.fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = ax = self.fig.add_axes((0.0, 0.0, 0.72, 0.90), projection="3d")
        ax.computed_zorder = False  # draw order = zorder: markers and arrows stay on top of the surface
        self.cmaps = {k: colormaps[v] for k, v in _CMAPS.items()}
        scene = core.scene
        mesh = scene.mesh
        self.tris = np.asarray(mesh.surface_tris, dtype=np.int64)
        x0 = np.asarray(scene.x_start)
        self.x0 = x0
        edges = np.asarray(scene.model.edges, dtype=np.int64)
        self.edges = edges
        self.len0 = np.maximum(np.linalg.norm(x0[edges[:, 0]] - x0[edges[:, 1]], axis=1), 1e-12)
        self.n_nodes = mesh.n_nodes
        self.surf = Poly3DCollection(x0[self.tris], edgecolor=(0.1, 0.1, 0.1, 0.2), linewidth=0.25, zorder=1)
        ax.add_collection3d(self.surf)
        g = scene.grasper
        corners = jaw_face_corners(scene.pose, scene.start_radius, g)
        self.jaws = Poly3DCollection(list(corners), facecolor=[(*_rgb(c), 0.45) for c in JAW_COLOURS],
                                     edgecolor="k", linewidth=0.8, zorder=2)
        ax.add_collection3d(self.jaws)
        (self.axis_line,) = ax.plot([], [], [], color="k", linewidth=1.0, linestyle="--")
        self.stick = ax.scatter([], [], [], color=STICK_COLOUR, s=9, depthshade=False, zorder=3)
        self.slip = ax.scatter([], [], [], color=SLIP_COLOUR, s=9, depthshade=False, zorder=3)
        self.arrows: list = []
        # camera: the grasped end of the organ, the jaws and the lift path (the anchored far end is cut off)
        pose = scene.pose
        span = 2.2 * g.jaw_length_m + core.config.lift_target_m
        near = np.linalg.norm(x0 - pose.tip, axis=1) < span
        lift = core.config.lift_target_m * 1.3
        pts = np.concatenate([x0[near], corners.reshape(-1, 3), corners.reshape(-1, 3) + lift * scene.pull_direction])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre = 0.5 * (lo + hi)
        half = 0.5 * float((hi - lo).max())
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.5)
        ax.view_init(elev=18.0, azim=-55.0)
        ax.set_axis_off()
        self.title = self.fig.text(0.01, 0.985, "", ha="left", va="top", fontsize=8, family="monospace")
        self.node_area = np.asarray(core.sim.node_area)
        # colour bar (its map and label follow color_by) and the marker legend
        self.cax = self.fig.add_axes((0.74, 0.56, 0.022, 0.30))
        self.cbar_key = None
        self.fig.text(0.85, 0.84, "\u25cf stick", color=STICK_COLOUR, fontsize=7, va="center")
        self.fig.text(0.85, 0.79, "\u25cf slip", color=SLIP_COLOUR, fontsize=7, va="center")
        self.fig.text(0.85, 0.74, "\u2192 normal", color="k", fontsize=7, va="center")
        self.fig.text(0.85, 0.69, "\u2192 friction", color="#ff7f0e", fontsize=7, va="center")
        # inset: pinch force and lift against time
        self.inset = ins = self.fig.add_axes((0.765, 0.10, 0.165, 0.33))
        self.inset_r = ins.twinx()
        t_end = core.config.time_limit_s
        ins.set_xlim(0.0, t_end)
        ins.set_ylim(0.0, core.config.max_pinch_force_N)
        self.inset_r.set_ylim(0.0, max(1.5 * core.config.lift_target_m, core.config.max_travel_m) * 1e3)
        self.inset_r.axhline(core.config.lift_target_m * 1e3, color="#d62728", linewidth=0.6, linestyle=":")
        (self.pinch_line,) = ins.plot([], [], color="k", linewidth=1.0)
        (self.lift_line,) = self.inset_r.plot([], [], color="#d62728", linewidth=1.0)
        ins.set_xlabel("t (s)", fontsize=6, labelpad=1)
        ins.set_ylabel("pinch (N)", fontsize=6, labelpad=1)
        self.inset_r.set_ylabel("lift (mm)", fontsize=6, color="#d62728", labelpad=1)
        for a in (ins, self.inset_r):
            a.tick_params(labelsize=5, pad=1, length=2)
        self.history: dict[int, list[tuple[float, float, float]]] = {}
        # blitting: everything static (colour bar, legend, inset frame) is drawn once into a background;
        # a frame restores it and draws only the animated artists (3 to 4x faster than a full draw)
        for artist in (ax, self.pinch_line, self.lift_line, self.title):
            artist.set_animated(True)
        self.background = None

    def _colour_bar(self, color_by: str) -> None:
        if self.cbar_key == color_by:
            return
        self.background = None
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        label, full = _COLOUR_LABELS[color_by]
        self.cax.clear()
        mappable = ScalarMappable(norm=Normalize(0.0, full), cmap=self.cmaps[color_by])
        bar = self.fig.colorbar(mappable, cax=self.cax)
        bar.set_label(label, fontsize=6, labelpad=2)
        bar.ax.tick_params(labelsize=5, length=2, pad=1)
        self.cbar_key = color_by

    def _node_values(self, core: Any, index: int, x: np.ndarray, color_by: str) -> np.ndarray:
        """Per-node value in the colour bar's unit."""
        if color_by == "pressure":
            area = np.maximum(self.node_area, 1e-12)
            value = np.linalg.norm(core.sim.contact_force[index], axis=1) / area / 1e3  # kPa
        elif color_by == "strain":
            e = self.edges
            strain = np.abs(np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / self.len0 - 1.0) * 100.0
            value = np.zeros(self.n_nodes)
            np.maximum.at(value, e[:, 0], strain)
            np.maximum.at(value, e[:, 1], strain)
        else:
            value = np.linalg.norm(x - self.x0, axis=1) * 1e3  # mm
        return np.where(np.isfinite(value), value, 0.0)

    def draw(self, core: Any, index: int, color_by: str) -> np.ndarray:
        sim = core.sim
        cfg = core.config
        x = np.asarray(sim.x[index])
        if not np.all(np.isfinite(x)):  # blown-up state: draw the start shape instead of failing
            x = np.where(np.isfinite(x), x, self.x0)
        self._colour_bar(color_by)
        full = _COLOUR_LABELS[color_by][1]
        face_val = self._node_values(core, index, x, color_by)[self.tris].max(axis=1) / full
        colours = self.cmaps[color_by](np.clip(face_val, 0.0, 1.0))
        colours[:, 3] = 0.85
        self.surf.set_verts(x[self.tris])
        self.surf.set_facecolor(colours)

        state = np.asarray(sim.contact_state[index])
        for artist, codes in ((self.stick, (STICK, WALL_STICK)), (self.slip, (SLIP, WALL_SLIP))):
            p = x[np.isin(state, codes)]
            artist._offsets3d = (p[:, 0], p[:, 1], p[:, 2])

        pose = GrasperPose(np.array(sim.g_tip[index]), np.array(sim.g_axis[index]), np.array(sim.g_e1[index]))
        radius = float(sim.g_radius[index])
        corners = jaw_face_corners(pose, radius, core.scene.grasper)
        for arrow in self.arrows:
            arrow.remove()
        self.arrows = []
        jo = np.asarray(sim.jaw_out[index])
        if np.all(np.isfinite(corners)):
            self.jaws.set_verts(list(corners))
            back = pose.tip - 1.5 * core.scene.grasper.jaw_length_m * pose.axis
            self.axis_line.set_data_3d([pose.tip[0], back[0]], [pose.tip[1], back[1]], [pose.tip[2], back[2]])
            u = pose.jaw_directions()
            for k in range(3):
                centre = corners[k].mean(axis=0)
                normal = -u[k] * jo[k, J_NORMAL]  # the jaw pushes the tissue toward the axis
                friction = jo[k, J_TX : J_TZ + 1]
                for vec, colour in ((normal, "k"), (friction, "#ff7f0e")):
                    if np.all(np.isfinite(vec)) and np.linalg.norm(vec) * ARROW_M_PER_N > 5e-4:
                        d = vec * ARROW_M_PER_N
                        self.arrows.append(self.ax.quiver(*centre, *d, color=colour, linewidth=1.4,
                                                          arrow_length_ratio=0.25, zorder=4))

        t = float(core.steps[index] * cfg.agent_dt_s)
        pinch = float(np.nansum(jo[:, J_NORMAL]))
        lift_mm = float(core.lift[index] * 1e3)
        hist = self.history.setdefault(index, [])
        if hist and t < hist[-1][0]:  # a new episode
            hist.clear()
        hist.append((t, pinch, lift_mm))
        h = np.asarray(hist)
        self.pinch_line.set_data(h[:, 0], h[:, 1])
        self.lift_line.set_data(h[:, 0], h[:, 2])
        self.title.set_text(
            f"mu={core.mu[index]:.2f}  t={t:5.2f}s  {outcome(core, index)}\n"
            f"pinch={pinch:4.2f}N  lift={lift_mm + 0.0:+5.1f}mm  jaw radius={radius * 1e3:4.1f}mm"
        )
        if self.background is None:
            self.canvas.draw()
            self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        self.canvas.restore_region(self.background)
        self.fig.draw_artist(self.ax)
        self.fig.draw_artist(self.pinch_line)
        self.fig.draw_artist(self.lift_line)
        self.fig.draw_artist(self.title)
        buf = np.asarray(self.canvas.buffer_rgba())
        img = buf[: self.height, : self.width, :3]
        if img.shape[:2] != (self.height, self.width):  # dpi rounding: pad to the requested size
            out = np.full((self.height, self.width, 3), 255, dtype=np.uint8)
            out[: img.shape[0], : img.shape[1]] = img
            return out
        return np.ascontiguousarray(img, dtype=np.uint8)


def outcome(core: Any, index: int) -> str:
    """The episode's state in words: gripping, lifting, holding (x%), held (success) or slipped."""
    cfg = core.config
    if core.lift_slip[index] > cfg.lift_slip_tolerance_m:
        return f"slipped ({core.lift_slip[index] * 1e3:.1f} mm since lifting began): no success"
    if core.hold_progress[index] >= 1.0:
        return "held: success"
    if core.hold_progress[index] > 0.0:
        return f"holding {100 * core.hold_progress[index]:3.0f}%"
    if core.lift_started[index]:
        return "lifting"
    return "gripping" if core.grip[index] > 0 or np.nansum(core.sim.jaw_out[index][:, J_NORMAL]) > 0.05 else "closing"


def _rgb(colour: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    return to_rgb(colour)


def render_rgb(core: Any, index: int, width: int = 640, height: int = 480, color_by: str = "strain") -> np.ndarray:
    """(height, width, 3) uint8 image of sub-env ``index`` of ``core`` (a :class:`GraspLiftCore`).

    ``color_by``: ``"strain"`` (largest spring strain at a node relative to the settled start, 0-20 %),
    ``"pressure"`` (nodal contact pressure, 0-60 kPa) or ``"displacement"`` (from the settled start, 0-40 mm).
    """
    if not 0 <= int(index) < core.num_envs:
        raise IndexError(f"index must be in [0, {core.num_envs - 1}], got {index}")
    if color_by not in COLOR_BY:
        raise ValueError(f"color_by must be one of {COLOR_BY}, got {color_by!r}")
    width, height = int(width), int(height)
    if width < 16 or height < 16:
        raise ValueError(f"image size must be at least 16 x 16 pixels, got {width} x {height}")
    cache: dict = getattr(core, "_render_cache", None) or {}
    frame = cache.get((width, height))
    if frame is None:
        frame = cache[(width, height)] = _Frame(core, width, height)
        core._render_cache = cache
    return frame.draw(core, int(index), color_by)
