"""Nonlinear viscoelastic mass-spring-damper (MSD) tissue built on a tetrahedral mesh.

Nodes are mesh vertices with lumped masses (density x tet volume / 4 per vertex, so the total mass is
exact); springs are the unique mesh edges with their rest lengths. Per-spring and per-node parameters
are plain arrays (:class:`TissueModel`), so any mixture of uniform and spatially varying values, and a
batch of tissues that differ only by scale factors, runs through the same numba kernels.

Two ways to set the springs (``TissueParams.stiffness_mode``):

``"uniform"``  the paper's way: every spring has the same K1 (N/m), K2 (N/m^3), dl_c (m) and every node
               the same b0 (N s/m), b1 (N s/m^2). Simple, but the organ's global stiffness then depends
               on the mesh resolution.
``"modulus"``  springs derived from a Young's modulus E (Pa): van Gelder (1998),
               K1 = sum over tets containing the edge of E V_tet / L^2, or Lloyd et al. (2007),
               K1 += (2 sqrt(2) / 25) E l_eq per tet, l_eq = (12 V / sqrt(2))^(1/3). The nonlinearity is
               given in strain so it is mesh independent: K2 = stiffening K1 / L0^2 (so that
               F = K1 dl (1 + stiffening (dl/L0)^2)), dl_c = critical_strain L0. Damping is mass
               proportional: b0_i = damping_rate m_i, b1_i = damping_disp_rate m_i.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .config import ConfigError, check_choice, check_range, check_vector
from .forces import accumulate_spring_forces, spring_energy
from .mesh import TetMesh


@dataclass(frozen=True)
class TissueParams:
    """Material parameters of the MSD tissue (SI units)."""

    stiffness_mode: Literal["modulus", "uniform"] = "modulus"
    density_kg_m3: float = 1054.0
    #: if set, the density is derived so that the total mass equals this (kg); overrides density_kg_m3
    mass_kg: float | None = None
    # -- "modulus" mode ------------------------------------------------------------------------
    youngs_modulus_pa: float = 12.0e3
    stiffness_rule: Literal["van_gelder", "lloyd"] = "van_gelder"
    #: dimensionless cubic stiffening: K2 = stiffening * K1 / L0^2
    stiffening: float = 10.0
    #: strain beyond which the spring law turns linear: dl_c = critical_strain * L0
    critical_strain: float = 0.2
    #: nodal damping per unit mass, 1/s: b0_i = damping_rate_per_s * m_i
    damping_rate_per_s: float = 200.0
    #: displacement-dependent nodal damping per unit mass, 1/(m s): b1_i = rate * m_i
    damping_disp_rate_per_m_s: float = 2.0e4
    # -- "uniform" mode (the paper's constants) ---------------------------------------------------
    k1_n_per_m: float = 50.0
    k2_n_per_m3: float = 5.0e5
    dl_c_m: float = 2.0e-3
    b0_n_s_per_m: float = 0.05
    b1_n_s_per_m2: float = 5.0
    # -- both modes -----------------------------------------------------------------------------
    #: Maxwell branch per spring (stress relaxation, see physics/viscoelastic.py): k_v = g * K1
    relaxation_strength: float = 0.0
    #: relaxation time constant tau of the Maxwell branch, s
    relaxation_time_s: float = 1.0
    #: linear dashpot along each spring, c = tau * K1 (s); 0 disables it
    spring_damping_time_s: float = 0.0
    gravity_m_per_s2: tuple[float, float, float] = (0.0, 0.0, -9.81)

    def __post_init__(self) -> None:
        check_choice("stiffness_mode", self.stiffness_mode, ("modulus", "uniform"))
        check_choice("stiffness_rule", self.stiffness_rule, ("van_gelder", "lloyd"))
        check_range("density_kg_m3", self.density_kg_m3, 0.0, None, lo_inclusive=False)
        if self.mass_kg is not None:
            check_range("mass_kg", self.mass_kg, 0.0, None, lo_inclusive=False)
        check_range("youngs_modulus_pa", self.youngs_modulus_pa, 0.0, None, lo_inclusive=False)
        check_range("stiffening", self.stiffening, 0.0, None)
        check_range("critical_strain", self.critical_strain, 0.0, None, lo_inclusive=False)
        check_range("damping_rate_per_s", self.damping_rate_per_s, 0.0, None)
        check_range("damping_disp_rate_per_m_s", self.damping_disp_rate_per_m_s, 0.0, None)
        check_range("k1_n_per_m", self.k1_n_per_m, 0.0, None, lo_inclusive=False)
        check_range("k2_n_per_m3", self.k2_n_per_m3, 0.0, None)
        check_range("dl_c_m", self.dl_c_m, 0.0, None, lo_inclusive=False)
        check_range("b0_n_s_per_m", self.b0_n_s_per_m, 0.0, None)
        check_range("b1_n_s_per_m2", self.b1_n_s_per_m2, 0.0, None)
        check_range("spring_damping_time_s", self.spring_damping_time_s, 0.0, None)
        check_range("relaxation_strength", self.relaxation_strength, 0.0, None)
        check_range("relaxation_time_s", self.relaxation_time_s, 0.0, None, lo_inclusive=False)
        object.__setattr__(self, "gravity_m_per_s2", check_vector("gravity_m_per_s2", self.gravity_m_per_s2))


def _edge_index(edges: np.ndarray, n_nodes: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Index into the sorted unique ``edges`` of the undirected pairs (a, b)."""
    lo = np.minimum(a, b).astype(np.int64)
    hi = np.maximum(a, b).astype(np.int64)
    keys = edges[:, 0].astype(np.int64) * n_nodes + edges[:, 1]
    q = lo * n_nodes + hi
    idx = np.searchsorted(keys, q)
    if np.any(idx >= len(keys)) or np.any(keys[np.minimum(idx, len(keys) - 1)] != q):
        raise ValueError("tet edge missing from the edge list (mesh edges are inconsistent)")
    return idx


_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


@dataclass(eq=False)
class TissueModel:
    """Static description of one MSD tissue: topology, rest state and per-spring/per-node arrays.

    Build with :meth:`from_params`. All arrays are float64/int64 and contiguous, ready for numba.
    """

    mesh: TetMesh
    params: TissueParams
    edges: np.ndarray  # (E,2) int64
    rest_length: np.ndarray  # (E,) m
    k1: np.ndarray  # (E,) N/m
    k2: np.ndarray  # (E,) N/m^3
    dlc: np.ndarray  # (E,) m
    cdash: np.ndarray  # (E,) N s/m
    mass: np.ndarray  # (N,) kg
    b0: np.ndarray  # (N,) N s/m
    b1: np.ndarray  # (N,) N s/m^2
    gravity: np.ndarray  # (3,) m/s^2
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))  # (N,) bool anchors
    kv: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (E,) Maxwell-branch stiffness, N/m
    #: (N,) stiffness of a linear spring tying each node to its rest position, N/m (compliant anchors:
    #: vessels and ligaments); 0 for free nodes
    anchor_k: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: (3,) rest offset of the compliant anchors, m: -M g / k_total, so that the anchors carry the organ's
    #: weight as a preload (ligaments under tension) and only *extra* loads stretch them
    anchor_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    # ------------------------------------------------------------------------------------------
    @classmethod
    def from_params(
        cls,
        mesh: TetMesh,
        params: TissueParams | None = None,
        fixed_nodes: np.ndarray | None = None,
        anchor_stiffness_n_per_m: float | None = None,
    ) -> "TissueModel":
        """Build the arrays. ``fixed_nodes`` are anchors: rigid (the paper) when
        ``anchor_stiffness_n_per_m`` is None, else each is tied to its rest position by a linear spring,
        the springs together giving ``anchor_stiffness_n_per_m`` (N/m)."""
        params = params or TissueParams()
        n = mesh.n_nodes
        edges = np.ascontiguousarray(mesh.edges, dtype=np.int64)
        x0 = mesh.nodes
        rest = np.linalg.norm(x0[edges[:, 1]] - x0[edges[:, 0]], axis=1)
        if np.any(rest <= 0):
            raise ValueError(f"mesh {mesh.name!r}: zero-length edge {int(np.argmin(rest))}")

        vol = mesh.tet_volumes
        density = params.density_kg_m3 if params.mass_kg is None else params.mass_kg / mesh.volume
        mass = np.zeros(n)
        np.add.at(mass, mesh.tets.ravel(), np.repeat(density * vol / 4.0, 4))

        if params.stiffness_mode == "uniform":
            k1 = np.full(len(edges), params.k1_n_per_m)
            k2 = np.full(len(edges), params.k2_n_per_m3)
            dlc = np.full(len(edges), params.dl_c_m)
            b0 = np.full(n, params.b0_n_s_per_m)
            b1 = np.full(n, params.b1_n_s_per_m2)
        else:
            tet_edge = _edge_index(
                edges, n, mesh.tets[:, _TET_EDGES[:, 0]].ravel(), mesh.tets[:, _TET_EDGES[:, 1]].ravel()
            )
            E = params.youngs_modulus_pa
            if params.stiffness_rule == "van_gelder":
                contrib = E * np.repeat(vol, 6) / rest[tet_edge] ** 2
            else:
                l_eq = (12.0 * vol / math.sqrt(2.0)) ** (1.0 / 3.0)
                contrib = np.repeat(2.0 * math.sqrt(2.0) / 25.0 * E * l_eq, 6)
            k1 = np.zeros(len(edges))
            np.add.at(k1, tet_edge, contrib)
            k2 = params.stiffening * k1 / rest**2
            dlc = params.critical_strain * rest
            b0 = params.damping_rate_per_s * mass
            b1 = params.damping_disp_rate_per_m_s * mass
        cdash = params.spring_damping_time_s * k1

        fixed = np.zeros(n, dtype=np.bool_)
        if fixed_nodes is not None:
            fixed_nodes = np.asarray(fixed_nodes, dtype=np.int64)
            if fixed_nodes.size and (fixed_nodes.min() < 0 or fixed_nodes.max() >= n):
                raise ValueError(f"fixed_nodes must be node indices in [0, {n - 1}]")
            fixed[fixed_nodes] = True
        anchor_k = np.zeros(n)
        anchor_offset = np.zeros(3)
        if anchor_stiffness_n_per_m is not None:
            check_range("anchor_stiffness_n_per_m", anchor_stiffness_n_per_m, 0.0, None, lo_inclusive=False)
            if fixed.any():
                anchor_k[fixed] = anchor_stiffness_n_per_m / fixed.sum()
                gravity = np.asarray(params.gravity_m_per_s2, dtype=np.float64)
                anchor_offset = -mass.sum() * gravity / anchor_stiffness_n_per_m
            fixed[:] = False
        return cls(
            mesh=mesh,
            params=params,
            edges=edges,
            rest_length=rest,
            k1=k1,
            k2=k2,
            dlc=dlc,
            cdash=cdash,
            mass=mass,
            b0=b0,
            b1=b1,
            gravity=np.asarray(params.gravity_m_per_s2, dtype=np.float64),
            fixed=fixed,
            kv=params.relaxation_strength * k1,
            anchor_k=anchor_k,
            anchor_offset=anchor_offset,
        )

    # ------------------------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return self.mesh.n_nodes

    @property
    def rest_positions(self) -> np.ndarray:
        return self.mesh.nodes

    @property
    def total_mass(self) -> float:
        return float(self.mass.sum())

    def tangent_stiffness_max(self) -> np.ndarray:
        """Largest instantaneous slope of each spring, B = K1 + 3 K2 dl_c^2 plus the Maxwell k_v (N/m)."""
        return self.k1 + 3.0 * self.k2 * self.dlc**2 + self.kv

    def omega_max(self, stiffness_scale: float = 1.0, mass_scale: float = 1.0) -> float:
        """Highest natural frequency (rad/s) of the linearised network at its stiffest slope.

        Largest eigenvalue of M^-1/2 K M^-1/2 with K assembled from B n n^T blocks at the rest
        configuration (scipy ``eigsh``); anchored nodes are excluded (they do not move). Falls back to
        the Gershgorin bound max_i 2 sum_j k_ij / m_i if the eigen-solver does not converge.
        """
        kt = self.tangent_stiffness_max() * stiffness_scale
        x0 = self.mesh.nodes
        d = x0[self.edges[:, 1]] - x0[self.edges[:, 0]]
        nrm = d / np.linalg.norm(d, axis=1, keepdims=True)
        blocks = kt[:, None, None] * nrm[:, :, None] * nrm[:, None, :]  # (E,3,3)
        i, j = self.edges[:, 0], self.edges[:, 1]
        n = self.n_nodes
        rows, cols, vals = [], [], []
        for a in range(3):
            for b in range(3):
                bv = blocks[:, a, b]
                rows += [3 * i + a, 3 * j + a, 3 * i + a, 3 * j + a]
                cols += [3 * i + b, 3 * j + b, 3 * j + b, 3 * i + b]
                vals += [bv, bv, -bv, -bv]
        K = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n)
        )
        free = np.repeat(~self.fixed if self.fixed.size else np.ones(n, bool), 3)
        m = np.repeat(self.mass * mass_scale, 3)
        s = 1.0 / np.sqrt(m[free])
        Kf = K[free][:, free]
        if self.anchor_k.size:
            Kf = Kf + sp.diags(np.repeat(self.anchor_k, 3)[free])
        A = sp.diags(s) @ Kf @ sp.diags(s)
        try:
            lam = float(spla.eigsh(A, k=1, which="LA", return_eigenvectors=False, tol=1e-3, maxiter=5000)[0])
        except (spla.ArpackNoConvergence, ValueError):
            deg = np.zeros(n)
            np.add.at(deg, i, kt)
            np.add.at(deg, j, kt)
            if self.anchor_k.size:
                deg = deg + self.anchor_k
            lam = float(np.max(2.0 * deg / (self.mass * mass_scale)))
        return math.sqrt(max(lam, 0.0))

    def critical_dt(self, stiffness_scale: float = 1.0, mass_scale: float = 1.0) -> float:
        """Stability limit (s) of the explicit (symplectic Euler) step.

        dt_crit = 2/omega_max for an undamped network; a spring dashpot (explicit) shortens it to
        2/omega (sqrt(1 + z^2) - z), z = omega c / (2 k). Nodal damping is implicit and costs nothing.
        """
        w = self.omega_max(stiffness_scale, mass_scale)
        if w == 0.0:
            return math.inf
        tau = self.params.spring_damping_time_s
        z = 0.5 * w * tau * self.k1.max() / self.tangent_stiffness_max().max()
        return 2.0 / w * (math.sqrt(1.0 + z * z) - z)

    # -- diagnostics (not hot paths) -----------------------------------------------------------
    def internal_forces(self, x: np.ndarray, v: np.ndarray | None = None, stiffness_scale: float = 1.0) -> np.ndarray:
        """Sum of spring (and dashpot, if ``v`` given) forces on each node (N,3), N."""
        f = np.zeros_like(x)
        vv = np.zeros_like(x) if v is None else np.ascontiguousarray(v)
        accumulate_spring_forces(
            np.ascontiguousarray(x), vv, self.edges, self.rest_length, self.k1, self.k2, self.dlc,
            self.cdash, stiffness_scale, v is not None and self.params.spring_damping_time_s > 0, f,
        )
        return f

    def elastic_energy(self, x: np.ndarray, stiffness_scale: float = 1.0) -> float:
        return stiffness_scale * spring_energy(
            np.ascontiguousarray(x), self.edges, self.rest_length, self.k1, self.k2, self.dlc
        )

    def kinetic_energy(self, v: np.ndarray, mass_scale: float = 1.0) -> float:
        return 0.5 * mass_scale * float(np.sum(self.mass[:, None] * v * v))

    def describe(self) -> dict:
        return {
            "nodes": self.n_nodes,
            "springs": int(len(self.edges)),
            "mass_kg": self.total_mass,
            "k1_mean_n_per_m": float(self.k1.mean()),
            "anchors": int(self.fixed.sum() + (self.anchor_k > 0).sum()),
        }


def check_dt(dt: float, dt_crit: float, what: str = "dt") -> None:
    """Refuse a forced time step beyond the stability limit with a clear message."""
    if not dt > 0:
        raise ConfigError(f"{what} must be > 0 s, got {dt!r}")
    if dt > dt_crit:
        raise ConfigError(
            f"{what} = {dt:.3e} s exceeds the explicit stability limit {dt_crit:.3e} s of this tissue "
            f"(2/omega_max at the stiffest spring slope); use substeps='auto' or {what} <= {dt_crit:.3e} s"
        )
