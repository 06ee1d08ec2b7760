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

What the modulus rule does and does not make resolution independent
-------------------------------------------------------------------
*Bulk.* Under an affine strain every tet's six springs store E V_tet sum_e (n_e . eps . n_e)^2 / 2
(van Gelder), so the energy density does not depend on the element size. On a Kuhn-split grid that
energy, averaged over mirrored cells in equal numbers, is a cubic crystal's, C11 = 1.444 E, C12 = C44 =
0.278 E, whose Voigt average is isotropic with the input E and nu = 1/4 (bulk modulus 2E/3 and shear
modulus 0.4 E both match); one unmirrored Kuhn lattice also couples shear to normal strain. The built-in
grids are mirrored per octant (:func:`.mesh_gen.kuhn_box`): within an octant every diagonal leans the
same way, so the network relaxes away from the affine strain, and relaxed it is neither that crystal
nor isotropic: a cube of it between frictionless plates is 18-21 % stiffer than E along a grid axis
with an effective Poisson ratio of 0.095-0.124 (``msdgrasp experiment fem``, docs/validation.md). A
central-force network cannot have a Poisson ratio other than 1/4 where it is isotropic.

*Contact.* A linear static solve of the sphere squeezed between frictionless plates (active-set contact,
:func:`plate_compression_force`) converges to the Hertz force of an elastic sphere with this E and
nu = 1/4 as the mesh is refined, but from above and slowly: at 10 % deformation the network force is
1.92 / 1.31 / 1.13 / 1.05 x Hertz with 5 / 9 / 15 / 24 cells across the diameter (coarse / medium /
fine / xfine); the excess falls like (h/a)^2 (h the edge length, a = sqrt(R D / 2) the Hertz contact
radius). Constant-strain tets cannot represent the contact stress field when a contact zone spans fewer
than a couple of elements, so a coarse mesh is too stiff in *contact*; its free-vibration modes and its
sag under gravity are, if anything, slightly too soft. A contact-calibrated modulus is therefore a
property of a load case, not of the material.

*Contact calibration* (``TissueParams.contact_calibration``). The paper tuned its spring constants per
mesh on the compression of a spherical sample. The analogue here, without measured data: for a
sphere-shaped mesh all springs are scaled by one factor c chosen so that the *linear* network, squeezed
between frictionless plates by D = 15 % of its height, gives the continuum Hertz force
F = (sqrt(2)/3) E* sqrt(R) D^(3/2), E* = E / (1 - nu^2), nu = 1/4. 15 % is the middle of the test's
deformation range, below the onset of tet inversion in every mesh up to ``fine`` (about 18 % at
6 mm/min), and the Hertz contact radius is still 0.39 R. c = 0.63 / 0.76 / 0.83 for coarse / medium /
fine; with it the plate force of the nonlinear, damped compression runs of the coarse and fine spheres
agrees within 1-6 % at 15 % deformation (60 and 6 mm/min) and 2 % at 20 % (60 mm/min). Below ~10 % the
coarse sphere still differs in *shape* (its poles are flat 4-node facets: F ~ D instead of D^1.5), which
no material factor can fix. Only a sphere has this analytic reference, so the calibration is opt-in:
``contact_calibration: hertz`` (set in ``configs/tissue/sphere.yaml``; ConfigError on a mesh whose
surface nodes are not on a sphere within 1 %); the default ``"none"`` keeps the van Gelder/Lloyd springs
(the spleen: there the coarse mesh is also slightly *softer* than the fine one under its own weight,
22 % more compliant with the hilum fixed, so a contact-derived factor would be wrong for it). The factor
is stored as :attr:`TissueModel.stiffness_correction`.

*Large compression.* A spring network resists a tet's inversion only through its edge lengths: beyond
~20-25 % global compression of the sphere, tets under the plates flatten and invert (finer meshes
earlier, since they resolve the larger local strains), and the force curve drops; under the env's jaws
(2.5 N pinch on the coarse spleen) tets reached J = V/V0 = -0.87. The volume barrier
(``volume_modulus_pa``, ``volume_threshold``; :func:`.forces.implicit_volume_barrier`) stores an energy
in tets that lost more than ``1 - volume_threshold`` of their volume, zero at the threshold and unbounded
as the volume goes to zero, so no finite load crushes a tet flat; below the threshold (everything up to
~20 % global compression of the sphere) the model is the paper's pure MSD. It is integrated implicitly, tet
by tet, before the contacts: it costs no substeps (the stability rule does not count it) and, being a force,
passes through a held node under the contact's friction law (physics/forces.py has the design).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from annotated_types import Gt, Le

from .config import ConfigError, NonNegative, Positive, Real, check_range, config_dataclass
from .forces import accumulate_spring_forces, spring_energy, volume_energy
from .mesh import TetMesh


@config_dataclass
class TissueParams:
    """Material parameters of the MSD tissue (SI units)."""

    stiffness_mode: Literal["modulus", "uniform"] = "modulus"
    density_kg_m3: Positive = 1054.0
    #: if set, the density is derived so that the total mass equals this (kg); overrides density_kg_m3
    mass_kg: Positive | None = None
    # -- "modulus" mode ------------------------------------------------------------------------
    youngs_modulus_pa: Positive = 12.0e3
    stiffness_rule: Literal["van_gelder", "lloyd"] = "van_gelder"
    #: "hertz": scale the modulus-derived springs so that the (sphere-shaped) mesh reproduces the Hertz
    #: plate-compression force at 15 % deformation (see the module docstring); "none": van Gelder/Lloyd as is
    contact_calibration: Literal["none", "hertz"] = "none"
    #: dimensionless cubic stiffening: K2 = stiffening * K1 / L0^2
    stiffening: NonNegative = 10.0
    #: strain beyond which the spring law turns linear: dl_c = critical_strain * L0
    critical_strain: Positive = 0.2
    #: nodal damping per unit mass, 1/s: b0_i = damping_rate_per_s * m_i
    damping_rate_per_s: NonNegative = 200.0
    #: displacement-dependent nodal damping per unit mass, 1/(m s): b1_i = rate * m_i
    damping_disp_rate_per_m_s: NonNegative = 2.0e4
    # -- "uniform" mode (the paper's constants) ---------------------------------------------------
    k1_n_per_m: Positive = 50.0
    k2_n_per_m3: NonNegative = 5.0e5
    dl_c_m: Positive = 2.0e-3
    b0_n_s_per_m: NonNegative = 0.05
    b1_n_s_per_m2: NonNegative = 5.0
    # -- both modes -----------------------------------------------------------------------------
    #: Maxwell branch per spring (stress relaxation, see physics/viscoelastic.py): k_v = g * K1
    relaxation_strength: NonNegative = 0.0
    #: relaxation time constant tau of the Maxwell branch, s
    relaxation_time_s: Positive = 1.0
    #: linear dashpot along each spring, c = tau * K1 (s); 0 disables it
    spring_damping_time_s: NonNegative = 0.0
    #: volume barrier against tet collapse and inversion (physics/forces.py): modulus k (Pa) of the energy
    #: k V0 psi(V / V0) of tets compressed below ``volume_threshold`` x their rest volume, psi unbounded as
    #: the volume goes to zero; 0 disables it (the pure MSD)
    volume_modulus_pa: NonNegative = 0.0
    #: J_c in (0, 1]: the barrier acts where V / V0 < J_c
    volume_threshold: Annotated[Real, Gt(0), Le(1)] = 0.5
    gravity_m_per_s2: tuple[Real, Real, Real] = (0.0, 0.0, -9.81)


def edge_index(edges: np.ndarray, n_nodes: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Index into the sorted unique ``edges`` of the undirected pairs (a, b)."""
    lo = np.minimum(a, b).astype(np.int64)
    hi = np.maximum(a, b).astype(np.int64)
    keys = edges[:, 0].astype(np.int64) * n_nodes + edges[:, 1]
    q = lo * n_nodes + hi
    idx = np.searchsorted(keys, q)
    if np.any(idx >= len(keys)) or np.any(keys[np.minimum(idx, len(keys) - 1)] != q):
        raise ValueError("tet edge missing from the edge list (mesh edges are inconsistent)")
    return idx


TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])

#: Poisson ratio of a central-force network (Cauchy relations; the Voigt average of the modulus rule)
NETWORK_POISSON_RATIO = 0.25
#: plate travel of the contact calibration, as a fraction of the sphere's height along z
CALIBRATION_DEFORMATION = 0.15
#: a mesh is "sphere-shaped" for ``contact_calibration="hertz"`` if its surface nodes lie within this
#: relative band of radii about their centroid
SPHERE_TOLERANCE = 0.01


def stiffness_matrix(nodes: np.ndarray, edges: np.ndarray, k: np.ndarray) -> sp.csr_matrix:
    """Linear stiffness matrix (3N x 3N, N/m) of a spring network at rest: sum of k n n^T blocks."""
    d = nodes[edges[:, 1]] - nodes[edges[:, 0]]
    nrm = d / np.linalg.norm(d, axis=1, keepdims=True)
    return assemble_edge_blocks(k[:, None, None] * nrm[:, :, None] * nrm[:, None, :], edges, len(nodes))


def assemble_edge_blocks(blocks: np.ndarray, edges: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """The 3N x 3N matrix of per-edge 3x3 blocks ``blocks`` (E,3,3): +B on both nodes' diagonal blocks, -B between
    them (a spring's stiffness, or its tangent)."""
    i, j = edges[:, 0], edges[:, 1]
    rows, cols, vals = [], [], []
    for a in range(3):
        for b in range(3):
            bv = blocks[:, a, b]
            rows += [3 * i + a, 3 * j + a, 3 * i + a, 3 * j + a]
            cols += [3 * i + b, 3 * j + b, 3 * j + b, 3 * i + b]
            vals += [bv, bv, -bv, -bv]
    n3 = 3 * n_nodes
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n3, n3))


def plate_compression_force(
    nodes: np.ndarray,
    edges: np.ndarray,
    k: np.ndarray,
    surface_nodes: np.ndarray,
    depth: float,
    axis: int = 2,
    max_iter: int = 50,
) -> tuple[float, int]:
    """Small-strain static compression of a linear spring network between two frictionless rigid plates.

    The plates are normal to ``axis``: one at the lowest node, one lowered by ``depth`` (m) from the
    highest. Contact is unilateral (surface nodes may not cross a plate; a plate may only push), found by
    an active-set iteration on the linear system (sparse LU, or Jacobi-preconditioned CG for large
    meshes). The in-plane rigid motions, free between frictionless plates, are removed by statically
    determinate pins (in-plane position of the node nearest the centroid, and one in-plane component of
    the node farthest from it along the first in-plane axis), which carry no load since every plate force
    is along ``axis``. Returns (total force of the moving plate on the body in N, its number of contact
    nodes).
    """
    n = len(nodes)
    K = stiffness_matrix(nodes, edges, k)
    z = nodes[:, axis]
    zmin, zmax = float(z.min()), float(z.max())
    tol = 1e-9 * (zmax - zmin)
    top_plane = zmax - depth
    surf = np.asarray(surface_nodes, dtype=np.int64)
    on_surf = np.zeros(n, dtype=bool)
    on_surf[surf] = True
    a1, a2 = [a for a in range(3) if a != axis]
    centre = nodes.mean(axis=0)
    pin_c = int(np.argmin(np.linalg.norm(nodes - centre, axis=1)))
    pin_f = int(np.argmax(np.abs(nodes[:, a1] - centre[a1])))
    pins = np.array([3 * pin_c + a1, 3 * pin_c + a2, 3 * pin_f + a2])
    # start from the nodes that a rigid approach of both plates by depth/2 would overlap (close to the
    # final contact zones of a body symmetric about its mid-plane, so the iteration needs few solves)
    top = on_surf & (z >= zmax - 0.5 * depth - tol)
    bot = on_surf & (z <= zmin + 0.5 * depth + tol)
    u = np.zeros(3 * n)
    for _ in range(max_iter):
        cons = np.flatnonzero(top | bot)
        cd = 3 * cons + axis
        fixed = np.zeros(3 * n, dtype=bool)
        fixed[cd] = True
        fixed[pins] = True
        free = ~fixed
        u_fixed = np.zeros(3 * n)
        u_fixed[cd] = np.where(top[cons], top_plane, zmin) - z[cons]
        A = K[free][:, free]
        rhs = -(K[free][:, fixed] @ u_fixed[fixed])
        if A.shape[0] <= 20000:
            u_free = spla.splu(A.tocsc()).solve(rhs)
        else:
            jac = 1.0 / A.diagonal()
            u_free, info = spla.cg(
                A, rhs, x0=u[free], rtol=1e-10, maxiter=20000,
                M=spla.LinearOperator(A.shape, matvec=lambda v: jac * v),
            )
            if info != 0:
                raise RuntimeError(f"plate compression: CG did not converge (info={info})")
        u = u_fixed
        u[free] = u_free
        r = (K @ u)[axis::3]  # force the plates exert on each node along the axis
        zn = z + u[axis::3]
        # a node is released only when the plate would pull it by more than round-off (exactly 0 can
        # flip sign between solves and cycle the active set)
        ftol = 1e-9 * float(np.max(np.abs(r))) if r.size else 0.0
        release_top = top & (r > ftol)
        release_bot = bot & (r < -ftol)
        add_top = on_surf & ~top & (zn > top_plane + tol)
        add_bot = on_surf & ~bot & (zn < zmin - tol)
        if not (release_top.any() or release_bot.any() or add_top.any() or add_bot.any()):
            break
        top = (top & ~release_top) | add_top
        bot = (bot & ~release_bot) | add_bot
    else:
        raise RuntimeError(f"plate contact active set did not converge in {max_iter} iterations")
    return float(-r[top].sum()), int(top.sum())


def hertz_sphere_force(youngs_modulus: float, radius: float, depth: float,
                       poisson: float = NETWORK_POISSON_RATIO) -> float:
    """Hertz force (N) of an elastic sphere squeezed between rigid plates by a total travel ``depth``:
    F = (sqrt(2)/3) E* sqrt(R) D^(3/2), E* = E / (1 - nu^2) (two Hertz contacts in series)."""
    e_star = youngs_modulus / (1.0 - poisson**2)
    return math.sqrt(2.0) / 3.0 * e_star * math.sqrt(radius) * depth**1.5


def sphere_radius(mesh: TetMesh, tolerance: float = SPHERE_TOLERANCE) -> float | None:
    """Radius (m) of the sphere the mesh's surface nodes lie on (within ``tolerance``), else None."""
    p = mesh.nodes[mesh.surface_nodes]
    # least-squares sphere (|p|^2 = 2 c.p + d is linear in c, d): the surface nodes' mean is off-centre
    # where the surface is sampled unevenly
    A = np.hstack([2.0 * p, np.ones((len(p), 1))])
    sol = np.linalg.lstsq(A, (p * p).sum(axis=1), rcond=None)[0]
    r = np.linalg.norm(p - sol[:3], axis=1)
    if r.max() <= 0.0 or (r.max() - r.min()) > tolerance * r.max():
        return None
    return float(r.max())


_CALIBRATION_CACHE: dict[tuple, float] = {}


def hertz_calibration_factor(mesh: TetMesh, k1: np.ndarray, youngs_modulus: float) -> float:
    """Factor c making the linear network ``k1`` on a sphere mesh reproduce the Hertz plate-compression
    force at a travel of :data:`CALIBRATION_DEFORMATION` x its height (see the module docstring).

    Cached per mesh geometry and spring set (c is independent of E when K1 is proportional to E).
    """
    radius = sphere_radius(mesh)
    if radius is None:
        raise ConfigError(
            f"contact_calibration='hertz' needs a sphere-shaped mesh (the compression sample: surface nodes "
            f"on a sphere within {SPHERE_TOLERANCE:.0%}); mesh {mesh.name!r} is not one; use contact_calibration='none'"
        )
    key = (
        hash(mesh.nodes.tobytes()), hash(mesh.tets.tobytes()), hash((k1 / youngs_modulus).round(12).tobytes()),
    )
    if key not in _CALIBRATION_CACHE:
        height = float(np.ptp(mesh.nodes[:, 2]))
        depth = CALIBRATION_DEFORMATION * height
        force, _ = plate_compression_force(mesh.nodes, mesh.edges, k1, mesh.surface_nodes, depth)
        _CALIBRATION_CACHE[key] = hertz_sphere_force(youngs_modulus, radius, depth) / force
    return _CALIBRATION_CACHE[key]


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
    #: factor applied to the modulus-derived springs by the contact calibration (1 = none)
    stiffness_correction: float = 1.0
    #: (T,) volume-barrier stiffness per tet, Pa (empty: no barrier); tets and rest volumes are the mesh's
    kvol: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def tets(self) -> np.ndarray:
        return self.mesh.tets

    @property
    def rest_volume(self) -> np.ndarray:
        return self.mesh.tet_volumes

    @property
    def volume_threshold(self) -> float:
        return self.params.volume_threshold

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
        correction = 1.0
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
            tet_edge = edge_index(
                edges, n, mesh.tets[:, TET_EDGES[:, 0]].ravel(), mesh.tets[:, TET_EDGES[:, 1]].ravel()
            )
            E = params.youngs_modulus_pa
            if params.stiffness_rule == "van_gelder":
                contrib = E * np.repeat(vol, 6) / rest[tet_edge] ** 2
            else:
                l_eq = (12.0 * vol / math.sqrt(2.0)) ** (1.0 / 3.0)
                contrib = np.repeat(2.0 * math.sqrt(2.0) / 25.0 * E * l_eq, 6)
            k1 = np.zeros(len(edges))
            np.add.at(k1, tet_edge, contrib)
            if params.contact_calibration == "hertz":
                correction = hertz_calibration_factor(mesh, k1, E)
                k1 = k1 * correction
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
            stiffness_correction=correction,
            # the barrier is scaled with the springs by the contact calibration, like the modulus it adds to
            kvol=(np.full(mesh.n_tets, params.volume_modulus_pa * correction) if params.volume_modulus_pa > 0
                  else np.zeros(0)),
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
        the Gershgorin bound (largest absolute row sum) if the eigen-solver does not converge.
        """
        kt = self.tangent_stiffness_max() * stiffness_scale
        n = self.n_nodes
        K = stiffness_matrix(self.mesh.nodes, self.edges, kt)
        # (the volume barrier is integrated implicitly, tet by tet: it does not bound the step)
        free = np.repeat(~self.fixed if self.fixed.size else np.ones(n, bool), 3)
        m = np.repeat(self.mass * mass_scale, 3)
        s = 1.0 / np.sqrt(m[free])
        Kf = K[free][:, free]
        if self.anchor_k.size:
            Kf = Kf + sp.diags(np.repeat(self.anchor_k, 3)[free])
        A = sp.diags(s) @ Kf @ sp.diags(s)
        try:
            # a fixed start vector: ARPACK's default is random, which made dt_crit (and so the automatic
            # substep count) differ from run to run by up to ~2e-4
            v0 = np.random.default_rng(0).uniform(0.5, 1.5, A.shape[0])
            lam = float(
                spla.eigsh(A, k=1, which="LA", return_eigenvectors=False, tol=1e-3, maxiter=5000, v0=v0)[0]
            )
        except (spla.ArpackNoConvergence, ValueError):
            lam = float(abs(A).sum(axis=1).max())  # Gershgorin bound
        return math.sqrt(max(lam, 0.0))

    def critical_dt(self, stiffness_scale: float = 1.0, mass_scale: float = 1.0) -> float:
        """Stability limit (s) of the explicit (symplectic Euler) step.

        dt_crit = 2/omega_max. Nodal damping, the spring dashpots and the volume barrier are integrated
        implicitly (:mod:`.integrator`) and do not shorten it.
        """
        w = self.omega_max(stiffness_scale, mass_scale)
        if w == 0.0:
            return math.inf
        return 2.0 / w

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
        """Potential energy (J) of the springs and of the volume barrier at positions ``x`` (N,3): the
        potential of :meth:`internal_forces` plus the barrier's forces (the Maxwell branch is not elastic)."""
        xc = np.ascontiguousarray(x)
        energy = spring_energy(xc, self.edges, self.rest_length, self.k1, self.k2, self.dlc)
        if self.kvol.size:
            energy += volume_energy(xc, self.tets, self.rest_volume, self.kvol, self.volume_threshold)
        return stiffness_scale * energy

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
