"""`Simulation`: a batch of tissues on one mesh, with a grasper and/or plates, stepped in one numba call.

This is the thin Python wrapper around :func:`.integrator.simulate`. It owns the state arrays (batch
first), checks the time step against the tissue's stability limit, and exposes the readouts a sensorised
grasper would give. Everything hot happens inside the kernel; nothing here loops over nodes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .config import ConfigError, check_choice, check_range
from .contact import (
    G_COLS,
    G_GAIN,
    G_PINCH,
    G_SETPOINT,
    G_VMAX,
    J_CONTACT,
    J_NORMAL,
    J_PEAK_PRESSURE,
    J_SLIP,
    J_SLIP_DIST,
    J_STICK,
    J_TX,
    J_TZ,
    J_WALL_X,
    J_WALL_Z,
    N_JAW_COLS,
    jaw_directions,
)
from .grasper import GrasperParams, GrasperPose
from .integrator import all_finite, batch_lanes, simulate
from .forces import WATCH_DELTA, min_volume_ratios
from .device_layout import PRECISIONS, with_precision
from .records import SimModel, SimReadout, SimState
from .tissue import TissueModel, check_dt
from .viscoelastic import elongations


@dataclass(frozen=True)
class Plate:
    """An infinite rigid plane: a point on it, the unit normal pointing into the tissue side, velocity."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mu: float = 0.0


def _batch(value, batch: int, name: str, shape: tuple[int, ...] = ()) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    try:
        arr = np.broadcast_to(arr, (batch, *shape)).copy()
    except ValueError:
        raise ConfigError(f"{name} must broadcast to shape {(batch, *shape)}, got {arr.shape}") from None
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be finite")
    return arr


#: fraction of the stability limit dt_crit (linearised at rest, stiffest slope) that "auto" substeps use.
#: The limit alone is not enough: a stretched network is stiffer than at rest (the springs' tension adds
#: transverse stiffness: omega_max of the coarse sphere at 30 % stretch is 1.02x the rest bound), and
#: symplectic Euler's energy error grows with (omega dt)^2. Measured (undamped, 1 s, max |E/E0 - 1|, coarse
#: sphere / medium sphere / coarse spleen after a 30 % stretch): 0.8 -> diverges / 45 % / 10 %,
#: 0.7 -> 9.6 / 8.0 / 4.2 %, 0.6 -> 2.2 / 2.2 / 1.4 %, 0.5 -> 0.7 / 0.6 / 0.4 %, with the volume barrier's
#: stiffness in the bound. The barrier is now implicit and not in the bound, which loosens it (the coarse sphere
#: without its dashpot: 3 substeps at 0.6, 9.4 % after a 25 % stretch, springs alone); at 0.5 the same case
#: takes 4 substeps (1.3 %), and the env's coarse spleen keeps its 3. The grasp readouts of the env's spleen
#: (pinch, pull force, slip under a 2.5 N pinch and a 20 mm/s pull) converge at 3 substeps (within 0.01 N and
#: 0.003 mm of 15 substeps) and not at 2 (pull force off by 0.05 N of 0.24, slip by 0.95 mm).
SUBSTEP_SAFETY = 0.5
#: where the kernel runs (Simulation(backend=...))
BACKENDS = ("cpu", "cuda")


class Simulation:
    """A batch of ``batch_size`` MSD tissues (same mesh, per-tissue scales/friction/grasper) in time.

    Parameters
    ----------
    model : TissueModel
    batch_size : int
    dt : float
        Outer physics step, s (default 1 ms = 1 kHz).
    substeps : int | "auto"
        Substeps per outer step. ``"auto"`` picks the fewest that keep the explicit scheme stable
        (``safety`` x critical step) for the stiffest/lightest tissue allowed by
        ``max_stiffness_scale`` / ``min_mass_scale``. A forced value beyond the limit raises ConfigError.
    safety : float
        Fraction of the linear stability limit a substep may use (default :data:`SUBSTEP_SAFETY`).
    grasper : GrasperParams | None
        Enables the three jaws (pose set with :meth:`set_grasper_pose`).
    plates : sequence of Plate
        Rigid planes (compression tests).
    backend : "cpu" | "cuda"
        Where :meth:`step` runs the kernel: numba on the CPU, or numba's CUDA target
        (:mod:`.cuda_step`: one thread block per tissue, same records; the state is copied to the GPU and
        back around each call, so everything else is unchanged). ``NUMBA_ENABLE_CUDASIM=1`` runs the CUDA
        kernel in numba's simulator on the CPU.
    precision : "float64" | "float32"
        The float type of the arrays of one entry per node, spring or tet (positions, velocities, Maxwell state,
        external forces, contact forces and the material arrays: :data:`.device_layout.FLOAT32_FIELDS`); the
        springs then compute in float32 (the largest phase of a substep), the rest of the step in float64 on the
        float32 arrays. float64 (the default) is the physics every experiment, env and result in this package
        uses; float32 is an option for throughput, its error against float64 stated in docs/performance.md
        (``msdgrasp bench physics``). On the CUDA backend it is the GPU kernel's own float32 storage.
    """

    def __init__(
        self,
        model: TissueModel,
        batch_size: int = 1,
        *,
        dt: float = 1e-3,
        substeps: int | str = "auto",
        grasper: GrasperParams | None = None,
        plates: Sequence[Plate] = (),
        max_stiffness_scale: float = 1.0,
        min_mass_scale: float = 1.0,
        safety: float = SUBSTEP_SAFETY,
        backend: str = "cpu",
        precision: str = "float64",
    ) -> None:
        if not isinstance(batch_size, (int, np.integer)) or batch_size < 1:
            raise ConfigError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        check_range("dt", dt, 0.0, None, lo_inclusive=False)
        check_range("max_stiffness_scale", max_stiffness_scale, 0.0, None, lo_inclusive=False)
        check_range("min_mass_scale", min_mass_scale, 0.0, None, lo_inclusive=False)
        check_range("safety", safety, 0.0, None, lo_inclusive=False)
        check_choice("backend", backend, BACKENDS)
        check_choice("precision", precision, PRECISIONS)
        self.backend = backend
        self.precision = precision
        real = np.float32 if precision == "float32" else np.float64
        self._model_record: tuple[SimModel, SimModel] | None = None  # (float32: the model and its cast)
        self._cuda = None  # physics.cuda_step.CudaBatch, made at the first step
        self.model = model
        self.batch_size = B = int(batch_size)
        self._lanes = batch_lanes(B)  # the batch's lane blocks for simulate (None below LANE_MIN), made once
        self.dt = float(dt)
        self.max_stiffness_scale = float(max_stiffness_scale)
        self.min_mass_scale = float(min_mass_scale)
        self.dt_crit = model.critical_dt(max_stiffness_scale, min_mass_scale)
        if substeps == "auto":
            self.n_sub = max(1, math.ceil(self.dt / (safety * self.dt_crit)))
        else:
            if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
                raise ConfigError(f"substeps must be 'auto' or an integer >= 1, got {substeps!r}")
            self.n_sub = int(substeps)
            check_dt(self.dt / self.n_sub, self.dt_crit, "dt / substeps")
        n = model.n_nodes
        mesh = model.mesh
        self.surface_nodes = np.ascontiguousarray(mesh.surface_nodes, dtype=np.int64)
        self.node_area = np.ascontiguousarray(mesh.surface_vertex_areas(), dtype=np.float64)
        self.use_dashpot = bool(model.params.spring_damping_time_s > 0.0)
        self.use_sls = bool(model.params.relaxation_strength > 0.0)
        #: m: how far a node may move (beyond a common translation) before the volume barrier's flag pass looks at
        #: every tet again (:data:`.forces.WATCH_DELTA` of the mean spring length; 0: every substep; bitwise the same)
        self.watch_delta = WATCH_DELTA * float(np.mean(model.rest_length)) if len(model.rest_length) else 0.0
        n_springs = len(model.edges)
        self.fv = np.zeros((B, n_springs), dtype=real)  # Maxwell-branch force per spring, N
        self.dl_prev = np.zeros((B, n_springs), dtype=real)  # spring elongation at the last substep, m

        self.x = np.empty((B, n, 3), dtype=real)
        self.v = np.empty((B, n, 3), dtype=real)
        self.t = np.zeros(B)
        self.kscale = np.ones(B)
        self.mscale = np.ones(B)
        self.f_ext = np.zeros((B, n, 3), dtype=real)

        self._init_grasper(grasper)
        self._init_plates(plates)

        self.jaw_out = np.zeros((B, 3, N_JAW_COLS))
        self.plate_out = np.zeros((B, len(self.plates), 3))
        self.anchor_out = np.zeros((B, 3))
        self.contact_state = np.zeros((B, n), dtype=np.int8)
        self.contact_force = np.zeros((B, n, 3), dtype=real)
        self.held = np.zeros((B, n), dtype=np.int8)
        self._finite = np.ones(B, dtype=np.bool_)
        self.reset()

    def _init_grasper(self, grasper: GrasperParams | None) -> None:
        """The grasper's per-tissue arrays: pose, jaw radius (m) and its limits, commands, force loop, friction."""
        B = self.batch_size
        self.grasper = grasper
        gp = grasper or GrasperParams()
        self.g_tip = np.zeros((B, 3))
        self.g_axis = np.tile([0.0, 0.0, 1.0], (B, 1))
        self.g_e1 = np.tile([1.0, 0.0, 0.0], (B, 1))
        self.g_radius = np.full(B, gp.open_radius_m)
        self.g_vradius = np.zeros(B)
        self.g_vpull = np.zeros((B, 3))
        self.g_rmin = np.full(B, gp.min_radius_m)
        self.g_rmax = np.full(B, gp.open_radius_m)
        # jaw force loop (off: set-point < 0): see command_pinch_force
        self.g_force = np.zeros((B, G_COLS))
        self.g_force[:, G_SETPOINT] = -1.0
        self.mu_s = np.full(B, gp.mu)
        self.mu_k = np.full(B, gp.mu_k)

    def _init_plates(self, plates: Sequence[Plate]) -> None:
        """The plates' arrays, checked: unit normals and friction (shared), start points (m) and velocities (m/s)."""
        B, P = self.batch_size, len(plates)
        self.plates = tuple(plates)
        self.pl_normal = np.zeros((P, 3))
        self.pl_point = np.zeros((B, P, 3))
        self.pl_vel = np.zeros((B, P, 3))
        self.pl_mu = np.zeros(P)
        for p, plate in enumerate(plates):
            nrm = np.asarray(plate.normal, dtype=np.float64)
            if nrm.shape != (3,) or not np.linalg.norm(nrm) > 0:
                raise ConfigError(f"plates[{p}].normal must be a non-zero 3-vector")
            check_range(f"plates[{p}].mu", plate.mu, 0.0, None)
            self.pl_normal[p] = nrm / np.linalg.norm(nrm)
            self.pl_mu[p] = plate.mu
        self._plate_init = np.array([p.point for p in plates], dtype=np.float64).reshape(P, 3)
        self._plate_vel = np.array([p.velocity for p in plates], dtype=np.float64).reshape(P, 3)

    # ------------------------------------------------------------------------------------------
    def _idx(self, indices) -> np.ndarray:
        if indices is None:
            return np.arange(self.batch_size)
        return np.atleast_1d(np.asarray(indices, dtype=np.int64))

    def reset(self, indices=None) -> None:
        """Tissues back at rest, jaws open, plates at their start, clocks at 0."""
        idx = self._idx(indices)
        self.x[idx] = self.model.rest_positions
        self.v[idx] = 0.0
        self.fv[idx] = 0.0
        self.dl_prev[idx] = 0.0
        self.t[idx] = 0.0
        self.f_ext[idx] = 0.0
        self.g_radius[idx] = self.g_rmax[idx]
        self.g_vradius[idx] = 0.0
        self.g_vpull[idx] = 0.0
        self.g_force[idx, G_SETPOINT] = -1.0
        self.g_force[idx, G_PINCH] = 0.0
        self.pl_point[idx] = self._plate_init
        self.pl_vel[idx] = self._plate_vel
        self.jaw_out[idx] = 0.0
        self.plate_out[idx] = 0.0
        self.anchor_out[idx] = 0.0
        self.contact_state[idx] = 0
        self.contact_force[idx] = 0.0
        self.held[idx] = 0

    def set_state(self, x: np.ndarray, indices=None, fv: np.ndarray | None = None) -> None:
        """Place tissues at positions ``x`` (N,3) at rest (v = 0), with Maxwell forces ``fv`` (default 0)."""
        idx = self._idx(indices)
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self.model.n_nodes, 3) or not np.all(np.isfinite(x)):
            raise ConfigError(f"state positions must be a finite ({self.model.n_nodes}, 3) array, got {x.shape}")
        self.x[idx] = x
        self.v[idx] = 0.0
        self.dl_prev[idx] = elongations(x, self.model.edges, self.model.rest_length)
        self.fv[idx] = 0.0 if fv is None else fv

    def set_scales(self, stiffness=None, mass=None, indices=None) -> None:
        """Per-tissue stiffness/mass multipliers (domain randomisation), within the stability bounds."""
        idx = self._idx(indices)
        if stiffness is not None:
            ks = _batch(stiffness, len(idx), "stiffness_scale")
            if np.any(ks <= 0) or np.any(ks > self.max_stiffness_scale * (1 + 1e-12)):
                raise ConfigError(
                    f"stiffness_scale must be in (0, {self.max_stiffness_scale}] (max_stiffness_scale), got {ks}"
                )
            self.kscale[idx] = ks
        if mass is not None:
            ms = _batch(mass, len(idx), "mass_scale")
            if np.any(ms < self.min_mass_scale * (1 - 1e-12)):
                raise ConfigError(f"mass_scale must be >= {self.min_mass_scale} (min_mass_scale), got {ms}")
            self.mscale[idx] = ms

    def set_friction(self, mu, mu_kinetic=None, indices=None) -> None:
        idx = self._idx(indices)
        mu = _batch(mu, len(idx), "mu")
        muk = mu if mu_kinetic is None else _batch(mu_kinetic, len(idx), "mu_kinetic")
        if np.any(mu < 0) or np.any(muk < 0) or np.any(muk > mu + 1e-12):
            raise ConfigError(f"friction must satisfy 0 <= mu_kinetic <= mu, got mu={mu}, mu_kinetic={muk}")
        self.mu_s[idx] = mu
        self.mu_k[idx] = muk

    def set_grasper_pose(self, pose: GrasperPose, indices=None, radius: float | None = None) -> None:
        idx = self._idx(indices)
        self.g_tip[idx] = pose.tip
        self.g_axis[idx] = pose.axis
        self.g_e1[idx] = pose.e1
        if radius is not None:
            self.g_radius[idx] = float(np.clip(radius, self.g_rmin[idx].min(), self.g_rmax[idx].max()))

    def command(self, closing_speed=None, pull_velocity=None, indices=None) -> None:
        """Jaw closing speed (m/s, > 0 closes, < 0 opens) and grasper pull velocity (m/s, 3-vector)."""
        idx = self._idx(indices)
        if closing_speed is not None:
            self.g_vradius[idx] = -_batch(closing_speed, len(idx), "closing_speed")
        if pull_velocity is not None:
            self.g_vpull[idx] = _batch(pull_velocity, len(idx), "pull_velocity", (3,))

    def command_pinch_force(self, setpoint_N, gain_m_s_per_N: float, max_speed_m_s, indices=None) -> None:
        """Hand the jaw radius to the 1 kHz pinch-force loop (a torque-controlled jaw motor): at every outer
        step the closing speed becomes ``gain * (setpoint - pinch of the last step)``, limited to
        ``max_speed_m_s``. A negative set-point switches the loop off; :meth:`command` then sets the speed."""
        idx = self._idx(indices)
        check_range("pinch-force gain (m/s/N)", gain_m_s_per_N, 0.0, None, lo_inclusive=False)
        self.g_force[idx, G_SETPOINT] = _batch(setpoint_N, len(idx), "pinch-force set-point")
        self.g_force[idx, G_GAIN] = gain_m_s_per_N
        vmax = _batch(max_speed_m_s, len(idx), "max closing speed")
        if np.any(vmax <= 0):
            raise ConfigError(f"max closing speed must be > 0 m/s, got {vmax}")
        self.g_force[idx, G_VMAX] = vmax

    def kernel_model(self) -> SimModel:
        """The constant half of a kernel call: mesh, material, grasper geometry, plates, time stepping."""
        tm, gp = self.model, self.grasper
        record = SimModel(
            x_rest=tm.rest_positions, edges=tm.edges, rest_length=tm.rest_length, k1=tm.k1, k2=tm.k2, dlc=tm.dlc,
            cdash=tm.cdash, use_dashpot=self.use_dashpot, use_sls=self.use_sls, kv=tm.kv,
            tau=float(tm.params.relaxation_time_s),
            tets=tm.tets, rest_volume=tm.rest_volume, kvol=tm.kvol, vol_threshold=float(tm.volume_threshold),
            watch_delta=self.watch_delta,
            mass=tm.mass, b0=tm.b0, b1=tm.b1, fixed=tm.fixed, anchor_k=tm.anchor_k, anchor_offset=tm.anchor_offset,
            gravity=tm.gravity, surface_nodes=self.surface_nodes, node_area=self.node_area,
            jaw_active=gp is not None,
            jaw_length=float(gp.jaw_length_m) if gp else 0.0,
            jaw_half_width=0.5 * float(gp.jaw_width_m) if gp else 0.0,
            jaw_depth=float(gp.jaw_depth_m) if gp else 0.0,
            pl_normal=self.pl_normal, pl_mu=self.pl_mu, dt_outer=self.dt, n_sub=self.n_sub,
        )
        if self.precision == "float64":
            return record
        # float32: the arrays cast once, again where a caller has replaced one since (the record kept, so an array
        # replaced is never mistaken for a new one at the same address)
        cached = self._model_record
        if cached is None or any(a is not b if isinstance(a, np.ndarray) else a != b
                                 for a, b in zip(cached[0], record)):
            self._model_record = cached = (record, with_precision(record, self.precision))
        return cached[1]

    def kernel_state(self) -> SimState:
        """The batch's state arrays (the kernel advances them in place)."""
        return SimState(
            x=self.x, v=self.v, t=self.t, fv=self.fv, dl_prev=self.dl_prev,
            kscale=self.kscale, mscale=self.mscale, f_ext=self.f_ext, mu_s=self.mu_s, mu_k=self.mu_k,
            g_tip=self.g_tip, g_axis=self.g_axis, g_e1=self.g_e1, g_radius=self.g_radius, g_vradius=self.g_vradius,
            g_vpull=self.g_vpull, g_rmin=self.g_rmin, g_rmax=self.g_rmax, g_force=self.g_force,
            pl_point=self.pl_point, pl_vel=self.pl_vel, held=self.held,
        )

    def kernel_readout(self) -> SimReadout:
        """The readout arrays the kernel fills."""
        return SimReadout(jaw_out=self.jaw_out, plate_out=self.plate_out, anchor_out=self.anchor_out,
                          contact_state=self.contact_state, contact_force=self.contact_force)

    def step(self, n_steps: int = 1, indices=None) -> None:
        """Advance the tissues by ``n_steps`` outer steps (n_steps x n_sub substeps) in one kernel call.

        ``indices`` (CPU backend): advance only these tissues; the others (and their readouts) stay as they
        are. Each tissue's trajectory is bitwise the same in any batch, so this changes nothing for the tissues
        advanced; it saves the work of tissues whose episodes have ended while others run on."""
        # records are rebuilt each call (a few microseconds): they alias the current arrays, whatever
        # a caller has assigned to the attributes since
        if indices is not None:
            idx = self._idx(indices)
            if idx.size and (idx.min() < 0 or idx.max() >= self.batch_size or np.unique(idx).size != idx.size):
                raise ConfigError(f"step indices must be distinct tissues in 0..{self.batch_size - 1}, got {idx}")
            if self.backend == "cuda":
                raise ConfigError("step indices: the cuda backend advances its whole resident batch; pass "
                                  "indices=None")
            if idx.size < self.batch_size:
                if idx.size:
                    self._step_subset(np.sort(idx), int(n_steps))
                return
        if self.backend == "cuda":
            state, out = self.kernel_state(), self.kernel_readout()
            if self._cuda is None:
                from .cuda_step import CudaBatch  # imports numba.cuda only when asked for

                self._cuda = CudaBatch(self.kernel_model(), state, out, precision=self.precision)
            else:  # the host arrays are the truth between calls: whatever a caller changed goes up
                self._cuda.upload(state, out)
            self._cuda.step(int(n_steps))
            self._cuda.download(state, out)
            return
        simulate(self.kernel_model(), self.kernel_state(), self.kernel_readout(), int(n_steps), self._lanes)

    def _step_subset(self, idx: np.ndarray, n_steps: int) -> None:
        """:meth:`step` of the tissues ``idx`` alone: their state and readouts gathered into a smaller batch,
        advanced, and written back."""
        state = SimState(*(a[idx] for a in self.kernel_state()))
        out = SimReadout(*(a[idx] for a in self.kernel_readout()))
        simulate(self.kernel_model(), state, out, n_steps, batch_lanes(idx.size))
        for dst, src in zip(self.kernel_state(), state):
            dst[idx] = src
        for dst, src in zip(self.kernel_readout(), out):
            dst[idx] = src

    # -- readouts ---------------------------------------------------------------------------------
    def finite(self) -> np.ndarray:
        """(B,) False where a tissue has blown up (non-finite state)."""
        all_finite(self.x, self.v, self._finite)
        return self._finite.copy()

    def min_volume_ratio(self) -> np.ndarray:
        """(B,) smallest current / rest tet volume of each tissue: <= 0 means a tet has inverted
        (the volume barrier acts below ``volume_threshold``)."""
        out = np.empty(self.batch_size)
        min_volume_ratios(self.x, self.model.tets, self.model.rest_volume, out)
        return out

    @property
    def jaw_normal_force(self) -> np.ndarray:
        """(B,3) normal force of each jaw on the tissue, N (averaged over the last 1 ms step)."""
        return self.jaw_out[:, :, J_NORMAL].copy()

    @property
    def jaw_tangential_force(self) -> np.ndarray:
        """(B,3,3) friction force vector of each jaw on the tissue, N."""
        return self.jaw_out[:, :, J_TX : J_TZ + 1].copy()

    def jaw_face_forces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each jaw's force on the tissue split by where it acts: (normal (B,3) N and friction (B,3,3) N of its
        gripping face, force (B,3,3) N of its side and end walls). The face's share is the jaw's readout less the
        walls' (the walls push nodes that reach round a jaw's edges: a geometric hook, not friction)."""
        wall = self.jaw_out[:, :, J_WALL_X : J_WALL_Z + 1].copy()
        u = np.empty((self.batch_size, 3, 3))
        tj = np.empty((3, 3))
        for b in range(self.batch_size):
            jaw_directions(self.g_axis[b], self.g_e1[b], u[b], tj)
        wall_normal = -np.einsum("bkc,bkc->bk", wall, u)
        normal = self.jaw_out[:, :, J_NORMAL] - wall_normal
        friction = self.jaw_out[:, :, J_TX : J_TZ + 1] - (wall + wall_normal[:, :, None] * u)
        return normal, friction, wall

    @property
    def pinch_force(self) -> np.ndarray:
        """(B,) total pinch force = sum of the jaws' normal forces, N."""
        return self.jaw_out[:, :, J_NORMAL].sum(axis=1)

    @property
    def jaw_contact_counts(self) -> np.ndarray:
        """(B,3,3) [contact, stick, slip] node counts per jaw (last substep)."""
        return self.jaw_out[:, :, [J_CONTACT, J_STICK, J_SLIP]].astype(np.int64)

    @property
    def jaw_slip_distance(self) -> np.ndarray:
        """(B,3) slip of the grasped surface relative to each jaw during the last call, m."""
        return self.jaw_out[:, :, J_SLIP_DIST].copy()

    @property
    def peak_contact_pressure(self) -> np.ndarray:
        """(B,) peak nodal normal stress under the jaws during the last call, Pa."""
        return self.jaw_out[:, :, J_PEAK_PRESSURE].max(axis=1)

    def tangential_force_along(self, direction) -> np.ndarray:
        """(B,) total friction force of the jaws on the tissue projected on ``direction`` (unit), N."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        ft = self.jaw_out[:, :, J_TX : J_TZ + 1].sum(axis=1)
        return np.einsum("bi,i->b", ft, d) if d.ndim == 1 else np.einsum("bi,bi->b", ft, d)

    def energies(self, index: int = 0) -> tuple[float, float]:
        """(kinetic, elastic) energy of tissue ``index``, J (gravity excluded)."""
        ke = self.model.kinetic_energy(self.v[index], self.mscale[index])
        pe = self.model.elastic_energy(self.x[index], self.kscale[index])
        return ke, pe
