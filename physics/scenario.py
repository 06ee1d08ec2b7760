"""Ready-made grasp scenes: the spleen hanging from its hilum under gravity, and the free test sphere.

A scene bundles the tissue model (anchors set), the grasper parameters, the *settled* initial state
(the organ after sagging under gravity, computed once and cached) and the grasper pose fitted to it.
Both the experiments and the Gymnasium env start from a scene, so they share one definition of "the
grasper around the inferior pole".
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from .config import GRASPER_FILE, TISSUE_FILE, ConfigError, builtin_config, from_dict, load_config
from .grasper import GrasperParams, GrasperPose, reachable_radius, start_radius
from .mesh import TetMesh
from .mesh_io import mesh_from_config, mesh_spec
from .simulation import SUBSTEP_SAFETY, Simulation
from .tissue import TissueModel, TissueParams

T = TypeVar("T")


@dataclass(eq=False)
class GraspScene:
    """Everything needed to start a grasp: model, grasper, settled state and pose."""

    name: str
    model: TissueModel
    grasper: GrasperParams
    x_start: np.ndarray  # (N,3) settled positions, m
    fv_start: np.ndarray  # (E,) Maxwell-branch forces of the settled state, N
    pose: GrasperPose
    #: radius at which the jaws start (just outside first contact), m
    start_radius: float
    #: unit direction in which the grasper pulls (away from the anchors)
    pull_direction: np.ndarray
    #: per jaw, the largest radius at which it touches tissue (0: that jaw never can)
    reach: np.ndarray

    @property
    def mesh(self) -> TetMesh:
        return self.model.mesh

    def simulation(self, batch_size: int = 1, **kwargs) -> Simulation:
        """A Simulation of this scene, all tissues at the settled state, jaws at the start radius."""
        sim = Simulation(self.model, batch_size, grasper=self.grasper, **kwargs)
        self.reset(sim)
        return sim

    def reset(self, sim: Simulation, indices=None) -> None:
        sim.reset(indices)
        idx = sim._idx(indices)
        sim.set_state(self.x_start, indices, self.fv_start)
        sim.set_grasper_pose(self.pose, indices)
        sim.g_radius[idx] = self.start_radius


#: the kind of config file each parameter section lives in
_FILE_OF_SECTION = {"tissue": TISSUE_FILE, "grasper": GRASPER_FILE}


def load_params(path: str | Path, section: str, cls: type[T]) -> T:
    """Record ``cls`` from section ``section`` (``tissue`` or ``grasper``) of a tissue or grasper config,
    strictly (:func:`.config.load_config`): a misspelt or missing section or an unknown key is a one-line
    :class:`ConfigError` naming the file and the key, never the defaults."""
    return load_config(cls, path, _FILE_OF_SECTION[section], section)


def check_scene_files(tissue_config: str | Path | None, grasper_config: str | Path | None, where: str = "env") -> None:
    """Load a scene's tissue config (sections, ``tissue:`` keys, ``mesh:`` section and mesh file) and grasper
    config strictly, without building the mesh: a run that will build the scene calls this before it writes
    anything, so a bad file fails as one :class:`ConfigError` line, not after the run folder is made. None:
    the built-in config, which needs no check. ``where`` names the config that names the files."""
    for key, value in (("tissue_config", tissue_config), ("grasper_config", grasper_config)):
        if value is not None and not Path(value).is_file():
            raise ConfigError(f"{where}.{key}: config file not found: {value}")
    if tissue_config is not None:
        load_params(tissue_config, "tissue", TissueParams)
        mesh_spec(tissue_config)
    if grasper_config is not None:
        load_params(grasper_config, "grasper", GrasperParams)


def resolve_scene_paths(env: dict | None, yaml_path: str | Path) -> dict | None:
    """The ``env:`` section of a YAML file with a relative ``tissue_config`` / ``grasper_config`` made absolute
    against the YAML's folder (a config and the files it names move together; the run's saved config then
    names them wherever it is read)."""
    if not isinstance(env, dict):
        return env  # (not a mapping: the record's loader says so)
    out = dict(env)
    for key in ("tissue_config", "grasper_config"):
        value = out.get(key)
        if isinstance(value, str) and value and not Path(value).is_absolute():
            out[key] = str(Path(yaml_path).resolve().parent / value)
    return out


def settle(
    model: TissueModel, x0: np.ndarray | None = None, time_s: float = 6.0, dt: float = 1e-3,
    safety: float = SUBSTEP_SAFETY,
) -> tuple[np.ndarray, np.ndarray]:
    """(positions m, Maxwell forces N) after ``time_s`` of damped motion under gravity from ``x0`` (rest).

    A damped relaxation to equilibrium, which does not depend on the step: the settled spleen differs by
    <= 3.4e-8 m (Maxwell forces by 4e-7 N) between ``safety`` 0.95 and 0.6 (measured)."""
    sim = Simulation(model, 1, dt=dt, safety=safety)
    if x0 is not None:
        sim.set_state(x0)
    sim.step(int(round(time_s / dt)))
    if not sim.finite()[0]:
        raise FloatingPointError("tissue became non-finite while settling under gravity")
    return sim.x[0].copy(), sim.fv[0].copy()


def fit_pole_pose(
    x: np.ndarray, pole_nodes: np.ndarray, outward_hint: np.ndarray, jaw_length: float, insert_depth: float,
    azimuth_rad: float = 0.0,
) -> GrasperPose:
    """Grasper pose around the pole region ``x[pole_nodes]``, axis pointing from outside in.

    The pole direction is taken from the region's centroid to the mean of its outermost 10% of nodes
    along ``outward_hint`` (robust to the organ's sag; a principal-component axis is not, because a
    pole region can be wider than long). The jaws reach ``insert_depth`` in from the outermost node
    and are centred on the centroid of the nodes they span.
    """
    pts = x[pole_nodes]
    c = pts.mean(axis=0)
    hint = np.asarray(outward_hint, dtype=np.float64) / np.linalg.norm(outward_hint)
    proj = (pts - c) @ hint
    outer = pts[proj >= np.quantile(proj, 0.9)]
    d = outer.mean(axis=0) - c
    d /= np.linalg.norm(d)
    s = (pts - c) @ d
    s_lo = s.max() - insert_depth
    span = (s >= s_lo) & (s <= s_lo + jaw_length)
    centre = pts[span].mean(axis=0) if np.any(span) else c
    tip = centre + (c @ d + s_lo - centre @ d) * d
    return GrasperPose.from_axis(tip, -d, up_hint=(0.0, 0.0, 1.0)).rotated(azimuth_rad)


def centre_jaws(points: np.ndarray, pose: GrasperPose, grasper: GrasperParams, iterations: int = 4):
    """Shift the grasper axis sideways so that all three jaws first touch the tissue at the same radius.

    Jaw k first touches at reach_k = max (x - c).u_k over the nodes on its footprint; moving the tip by
    delta (normal to the axis) changes it by -delta.u_k. Since u_0 + u_1 + u_2 = 0 the mean reach is
    unchanged and two equations fix delta; repeated because the footprints change with delta.
    """
    reach = reachable_radius(points, pose, grasper)
    for _ in range(iterations):
        if np.any(reach <= 0):
            break
        u = pose.jaw_directions()
        e1 = pose.e1
        e2 = np.cross(pose.axis, e1)
        A = np.array([[u[k] @ e1, u[k] @ e2] for k in range(2)])
        rhs = reach[:2] - reach.mean()
        a, b = np.linalg.solve(A, rhs)
        trial = GrasperPose(pose.tip + a * e1 + b * e2, pose.axis, pose.e1)
        trial_reach = reachable_radius(points, trial, grasper)
        if np.any(trial_reach <= 0) or np.ptp(trial_reach) >= np.ptp(reach):
            break  # a jaw would lose its footprint, or no improvement: keep the last good pose
        pose, reach = trial, trial_reach
    return pose, reachable_radius(points, pose, grasper)


@functools.lru_cache(maxsize=16)
def _spleen_scene_cached(
    tissue_cfg: str, grasper_cfg: str, resolution, insert_depth_m: float, settle_s: float, azimuth_deg: float,
    anchor_stiffness_n_per_m: float | None,
) -> GraspScene:
    params = load_params(tissue_cfg, "tissue", TissueParams)
    grasper = load_params(grasper_cfg, "grasper", GrasperParams)
    mesh = mesh_from_config(tissue_cfg, resolution)
    if "hilum" not in mesh.node_sets or "inferior_pole" not in mesh.node_sets:
        raise ConfigError(
            f"mesh {mesh.name!r} needs node sets 'hilum' (anchors) and 'inferior_pole' (grasp region); "
            f"it has {sorted(mesh.node_sets)}"
        )
    model = TissueModel.from_params(mesh, params, fixed_nodes=mesh.node_sets["hilum"],
                                    anchor_stiffness_n_per_m=anchor_stiffness_n_per_m)
    x_start, fv_start = settle(model, time_s=settle_s)
    hint = mesh.landmarks.get("inferior_pole_axis", np.array([1.0, 0.0, 0.0]))
    pose = fit_pole_pose(x_start, mesh.node_sets["inferior_pole"], hint, grasper.jaw_length_m, insert_depth_m,
                         math.radians(azimuth_deg))
    pose, reach = centre_jaws(x_start[mesh.surface_nodes], pose, grasper)
    start = start_radius(reach, grasper)
    return GraspScene("spleen", model, grasper, x_start, fv_start, pose, start, -pose.axis, reach)


def spleen_scene(
    tissue_config: str | Path | None = None,
    grasper_config: str | Path | None = None,
    resolution: str | int | None = None,
    insert_depth_m: float | None = None,
    settle_s: float = 6.0,
    azimuth_deg: float = 0.0,
    anchor_stiffness_n_per_m: float | None = None,
) -> GraspScene:
    """The spleen anchored at its hilum, settled under gravity, grasper around the inferior pole.

    Anchors are rigid (the paper) unless ``anchor_stiffness_n_per_m`` gives the total stiffness of
    compliant anchors (hilum vessels and ligaments as springs).
    ``insert_depth_m`` (default 35 mm) is how far the jaw tips reach over the pole from its tip: a little
    more than the jaw length, so the jaws hold where the pole is nearly cylindrical (a tapered region
    with taper angle alpha squirts out of a grasp unless mu > tan(alpha)).
    Scenes are cached per arguments (the settling run is done once per process).
    """
    tcfg = str(Path(tissue_config or builtin_config("tissue/spleen.yaml")).resolve())
    gcfg = str(Path(grasper_config or builtin_config("grasper/default.yaml")).resolve())
    depth = 0.035 if insert_depth_m is None else float(insert_depth_m)
    if not depth > 0:
        raise ConfigError(f"insert_depth_m must be > 0, got {insert_depth_m!r}")
    return _spleen_scene_cached(tcfg, gcfg, resolution, depth, float(settle_s), float(azimuth_deg),
                                None if anchor_stiffness_n_per_m is None else float(anchor_stiffness_n_per_m))


def sphere_scene(
    tissue_config: str | Path | None = None,
    grasper_config: str | Path | None = None,
    resolution: str | int | None = None,
) -> GraspScene:
    """The free test sphere (no gravity, no anchors), the jaws centred on it, axis vertical."""
    tcfg = Path(tissue_config or builtin_config("tissue/sphere.yaml"))
    gcfg = Path(grasper_config or builtin_config("grasper/default.yaml"))
    params = load_params(tcfg, "tissue", TissueParams)
    params = from_dict(TissueParams, {**params.__dict__, "gravity_m_per_s2": (0.0, 0.0, 0.0)})
    grasper = load_params(gcfg, "grasper", GrasperParams)
    mesh = mesh_from_config(tcfg, resolution)
    model = TissueModel.from_params(mesh, params)
    centre = mesh.nodes.mean(axis=0)
    axis = np.array([0.0, 0.0, -1.0])
    pose = GrasperPose.from_axis(centre + 0.5 * grasper.jaw_length_m * axis, axis, up_hint=(1.0, 0.0, 0.0))
    x_start = mesh.nodes.copy()
    reach = reachable_radius(x_start[mesh.surface_nodes], pose, grasper)
    start = start_radius(reach, grasper)
    fv_start = np.zeros(len(model.edges))
    return GraspScene("sphere", model, grasper, x_start, fv_start, pose, start, np.array([0.0, 0.0, 1.0]), reach)
