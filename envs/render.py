"""Headless RGB rendering of a GraspLift sub-env (matplotlib Agg, no display, no pyplot state).

:func:`render_rgb` draws the deformed tissue surface of sub-env ``index`` of a :class:`GraspLiftCore`,
coloured by nodal displacement from the settled start state (or by nodal contact stress), the three jaw
faces at the grasper's current pose and radius, the anchor nodes as dots and a one-line status. One
matplotlib Figure per core and image size is built on the first call and cached on the core
(``core._render_cache``); later frames only update the artists' vertices and colours, so a frame costs
one Agg draw (a few ms for the coarse mesh). Works with ``gymnasium.wrappers.RecordVideo``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..physics.grasper import GrasperPose, jaw_face_corners

#: colour scales: displacement in mm, contact stress in kPa (full scale of the colour map)
DISP_FULL_SCALE_MM = 30.0
STRESS_FULL_SCALE_KPA = 60.0
JAW_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd")
COLOR_BY = ("displacement", "pressure")


class _Frame:
    """The cached figure of one core and image size."""

    def __init__(self, core: Any, width: int, height: int) -> None:
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        dpi = 100
        self.width, self.height = width, height
        self.fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        self.ax = ax = self.fig.add_axes((0.0, 0.0, 1.0, 0.93), projection="3d")
        self.cmap = colormaps["viridis"]
        self.cmap_p = colormaps["inferno"]
        scene = core.scene
        mesh = scene.mesh
        self.tris = np.asarray(mesh.surface_tris, dtype=np.int64)
        x0 = np.asarray(scene.x_start)
        self.x0 = x0
        self.surf = Poly3DCollection(x0[self.tris], edgecolor=(0.1, 0.1, 0.1, 0.25), linewidth=0.3)
        ax.add_collection3d(self.surf)
        g = scene.grasper
        corners = jaw_face_corners(scene.pose, core.start_radius, g)
        self.jaws = Poly3DCollection(list(corners), facecolor=[(*_rgb(c), 0.55) for c in JAW_COLOURS],
                                     edgecolor="k", linewidth=0.8)
        ax.add_collection3d(self.jaws)
        (self.axis_line,) = ax.plot([], [], [], color="k", linewidth=1.0, linestyle="--")
        model = scene.model
        anchors = np.zeros(mesh.n_nodes, dtype=bool)
        fixed = np.asarray(getattr(model, "fixed", np.zeros(0, dtype=bool)), dtype=bool)
        if fixed.size == mesh.n_nodes:
            anchors |= fixed
        anchor_k = np.asarray(getattr(model, "anchor_k", np.zeros(0)))
        if anchor_k.size == mesh.n_nodes:
            anchors |= anchor_k > 0
        self.anchor_idx = np.flatnonzero(anchors)
        pa = x0[self.anchor_idx] if self.anchor_idx.size else np.zeros((0, 3))
        self.anchor_pts = ax.scatter(pa[:, 0], pa[:, 1], pa[:, 2], color="#d62728", s=14, depthshade=False)
        # fixed limits: the settled tissue, the open jaws and the lift target along the pull direction
        lift = core.config.lift_target_m * 1.5
        pts = np.concatenate([x0, corners.reshape(-1, 3), corners.reshape(-1, 3) + lift * scene.pull_direction])
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre = 0.5 * (lo + hi)
        half = 0.5 * float((hi - lo).max()) * 0.9
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.45)
        ax.view_init(elev=20.0, azim=-60.0)
        ax.set_axis_off()
        self.title = self.fig.text(0.01, 0.985, "", ha="left", va="top", fontsize=7, family="monospace")
        self.node_area = np.asarray(core.sim.node_area)

    def draw(self, core: Any, index: int, color_by: str) -> np.ndarray:
        sim = core.sim
        x = np.asarray(sim.x[index])
        if not np.all(np.isfinite(x)):  # blown-up state: draw the start shape instead of failing
            x = np.where(np.isfinite(x), x, self.x0)
        if color_by == "pressure":
            area = np.maximum(self.node_area, 1e-12)
            value = np.linalg.norm(sim.contact_force[index], axis=1) / area / 1e3  # kPa
            value = np.where(np.isfinite(value), value, 0.0)
            face_val = value[self.tris].max(axis=1) / STRESS_FULL_SCALE_KPA
            colours = self.cmap_p(np.clip(0.15 + 0.85 * face_val, 0.0, 1.0))
        else:
            disp = np.linalg.norm(x - self.x0, axis=1) * 1e3  # mm
            face_val = disp[self.tris].mean(axis=1) / DISP_FULL_SCALE_MM
            colours = self.cmap(np.clip(face_val, 0.0, 1.0))
        colours[:, 3] = 0.9
        self.surf.set_verts(x[self.tris])
        self.surf.set_facecolor(colours)

        pose = GrasperPose(np.array(sim.g_tip[index]), np.array(sim.g_axis[index]), np.array(sim.g_e1[index]))
        radius = float(sim.g_radius[index])
        corners = jaw_face_corners(pose, radius, core.scene.grasper)
        if np.all(np.isfinite(corners)):
            self.jaws.set_verts(list(corners))
            back = pose.tip - 1.5 * core.scene.grasper.jaw_length_m * pose.axis
            self.axis_line.set_data_3d([pose.tip[0], back[0]], [pose.tip[1], back[1]], [pose.tip[2], back[2]])
        if self.anchor_idx.size:
            pa = x[self.anchor_idx]
            self.anchor_pts._offsets3d = (pa[:, 0], pa[:, 1], pa[:, 2])

        jo = sim.jaw_out[index]
        pinch = float(np.nansum(jo[:, 0]))
        self.title.set_text(
            f"#{index} t={core.steps[index] * core.config.agent_dt_s:.2f}s mu={core.mu[index]:.2f} "
            f"R={radius * 1e3:.1f}mm pinch={pinch:.2f}N lift={core.lift[index] * 1e3:.1f}mm"
        )
        self.canvas.draw()
        buf = np.asarray(self.canvas.buffer_rgba())
        img = buf[: self.height, : self.width, :3]
        if img.shape[:2] != (self.height, self.width):  # dpi rounding: pad to the requested size
            out = np.full((self.height, self.width, 3), 255, dtype=np.uint8)
            out[: img.shape[0], : img.shape[1]] = img
            return out
        return np.ascontiguousarray(img, dtype=np.uint8)


def _rgb(colour: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    return to_rgb(colour)


def render_rgb(core: Any, index: int, width: int = 480, height: int = 360, color_by: str = "displacement") -> np.ndarray:
    """(height, width, 3) uint8 image of sub-env ``index`` of ``core`` (a :class:`GraspLiftCore`).

    ``color_by``: ``"displacement"`` (nodal displacement from the settled start, 0-30 mm, viridis) or
    ``"pressure"`` (nodal contact stress, 0-60 kPa, inferno).
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
