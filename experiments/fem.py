"""A finite-element reference for the mass-spring network, on the same meshes and load cases.

What is compared. The MSD's springs are derived from a Young's modulus E (van Gelder or Lloyd,
:mod:`~msdgrasp.physics.tissue`). Here the same tets carry a continuum solid with that E: linear P1 elasticity at
small strain and a compressible neo-Hookean solid, W = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2, at large strain
(scikit-fem, the optional extra ``fem``; imported inside the functions that need it). Both models see the same
prescribed node displacements (:class:`LoadCase`): nodes moved by a rigid indenter or plate, nodes held on the far
side, every other node free; the force is the indenter's total reaction along the loading axis, N.

Quasi-static MSD. The network's equilibrium under the prescribed displacements is solved directly (Newton on the
springs' energy, the volume barrier included; :func:`msd_forces`): the state a damped run relaxes to once the
Maxwell branches have relaxed, i.e. the relaxed (long-time) modulus E the springs are derived from. The residual is
the kernel's own force law (:meth:`~msdgrasp.physics.tissue.TissueModel.internal_forces` and
:func:`~msdgrasp.physics.forces.volume_forces`).

Load cases (all loaded along z):

* ``cube`` (bonded): a cube between two plates glued to it (top face moved down, bottom face held, every
  component prescribed; the sides free to bulge), on a Kuhn-split grid as the built-in meshes use;
* ``cube-slip``: the same cube between frictionless plates (only z prescribed on the faces, rigid motions pinned):
  uniform uniaxial stress, so the lateral expansion gives the effective Poisson ratio of the network;
* ``sphere``: the shipped gmsh sphere indented at its top pole by a bonded flat punch (the surface nodes within
  :data:`INDENTER_RADIUS_FRACTION` R of the pole axis), the same patch at the bottom held;
* ``spleen``: the built-in spleen indented through its thickness at the middle of its long axis (surface nodes
  within :data:`SPLEEN_INDENTER_RADIUS_M` of the top point) with the opposite patch held; ``spleen-even``: the same
  surface filled with unstructured tets (:func:`~msdgrasp.physics.mesh_io.spleen_even_mesh`), the same patches;
* ``<body>-pad``: the sphere's or a spleen's two patches squeezed together by forces, not displacements (a traction
  on each patch's faces, :meth:`LoadCase.unit_load`), so that both models carry the same load;
* ``cube-j1``, ``cube-slip-j1``: the cubes on the alternating (J1) grid, where :func:`grid_springs` applies;
  ``spleen-j1``, ``spleen-j1-pad``: the built-in spleen's nodes on that grid, each axis's first and last cells pointing
  outward along it (:func:`~msdgrasp.physics.mesh_gen.kuhn_box`'s ``alternating-shell``; the same patches).

Strain is the indenter's travel (for the pads: their approach, f . u) over the case's height along z. The continuum
Poisson ratio is a parameter: 0.25 is the isotropic network's own (Cauchy relations;
:data:`~msdgrasp.physics.tissue.NETWORK_POISSON_RATIO`), the fair test of the discretisation; a near-incompressible
tissue (0.45-0.49) shows what the network's fixed ratio costs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..physics.config import ConfigError, from_dict, needs_extra, to_dict
from ..physics.forces import volume_forces
from ..physics.mesh import TetMesh, boundary_faces, tet_signed_volumes
from ..physics.mesh_io import sphere_even_mesh, spleen_even_mesh, spleen_j1_mesh
from ..physics.mesh_gen import kuhn_box, kuhn_lattice, spleen_lattice, spleen_mesh
from ..physics.reference import numpy_barrier_slopes, numpy_spring_law
from ..physics.tissue import (TET_EDGES, TissueModel, TissueParams, assemble_edge_blocks, edge_index,
                              hertz_sphere_force)

#: the load cases :func:`load_case` builds
CASES = ("cube", "cube-slip", "sphere", "spleen", "sphere-pad", "spleen-pad", "spleen-even", "spleen-even-pad",
         "cube-j1", "cube-slip-j1", "spleen-j1", "spleen-j1-pad")
#: cells per cube edge for the named resolutions (about the node counts of the built-in meshes')
CUBE_CELLS = {"coarse": 5, "medium": 8, "fine": 12}
#: the cube's edge, m (a grasped slab of spleen: its thickness is ~40 mm)
CUBE_SIDE_M = 0.03
#: radius of the bonded punch on the sphere, as a fraction of the sphere radius
INDENTER_RADIUS_FRACTION = 0.4
#: radius of the bonded punch (and of the held patch) on the spleen, m
SPLEEN_INDENTER_RADIUS_M = 0.012
#: the cases also solved at the large strains (cube-slip measures the Poisson ratio; no force-loaded large-strain path
#: is built for the pads; the J1 cube and spleen-even are calibrations compared at small strain)
LARGE_STRAIN_CASES = ("cube", "sphere", "spleen", "spleen-j1")
#: strains of the comparison: small (linear) and large (neo-Hookean)
SMALL_STRAIN = 0.02
LARGE_STRAINS = (0.10, 0.20)
#: each punch case and the squeeze between pads on the same mesh: the two loads of the continuum fit's cross-check
LOAD_PAIRS = tuple((c, c + "-pad") for c in CASES if c + "-pad" in CASES)
#: the acceptance band of the small-strain comparison (|MSD / FEM - 1|)
SMALL_STRAIN_RTOL = 0.10
#: the closed-form checks of the FEM solver must hold to this relative error before it is a reference
FEM_CHECK_RTOL = 0.02


def _skfem():
    with needs_extra("fem", "the finite-element reference (scikit-fem)"):
        import skfem
    return skfem


# =================================================================================================
# meshes and load cases
# =================================================================================================


def cube_mesh(side_m: float = CUBE_SIDE_M, cells: int = 5, pattern: str = "octant") -> TetMesh:
    """A cube of edge ``side_m`` (m) centred on the origin, ``cells`` cells per edge, each split into six Kuhn
    tets: reflected about the centre planes (``pattern`` octant, as the built-in meshes' grids are) or cell by cell
    (alternating: Todd's J1; :func:`~msdgrasp.physics.mesh_gen.kuhn_box`)."""
    if not (isinstance(cells, (int, np.integer)) and cells >= 1):
        raise ConfigError(f"cube cells must be an integer >= 1, got {cells!r}")
    if not (math.isfinite(side_m) and side_m > 0):
        raise ConfigError(f"cube side_m must be > 0, got {side_m!r}")
    n = int(cells)
    grid, t = kuhn_box((n, n, n), pattern)  # (on [-1, 1]^3)
    nodes = 0.5 * side_m * grid
    surface = np.unique(boundary_faces(t, "cube"))
    return TetMesh(nodes, t, node_sets={"surface": surface}, name=f"cube-{n}" + ("-j1" if pattern != "octant" else ""))


@dataclass
class LoadCase:
    """Prescribed node displacements along z: ``moved`` nodes travel -z by the indenter's travel, ``held`` nodes
    stay; ``bonded``: every component of those nodes is prescribed (glued plates / punch), else only z, with
    ``pins`` (node, axis) removing the free rigid motions.

    With ``pad_weights`` the case is loaded by forces instead (a squeeze between two pads): ``moved`` and ``held``
    are the pads' node sets, nothing of theirs is prescribed, and each pad's faces (the surface faces whose three
    nodes are all in its set) carry a traction along z, linear in x and y with the coefficients ``pad_weights``
    (c0, cx, cy) per pad, 1 N in all, pushing the two pads together in moment balance; the ``pins`` only remove the
    rigid motions (they carry no load). Both models get the same nodal forces (:meth:`unit_load`), and the travel is
    the pads' approach that does work on them (:meth:`unit_load` . u, per newton)."""

    name: str
    mesh: TetMesh
    moved: np.ndarray
    held: np.ndarray
    bonded: bool
    #: the case's height along z (strain = travel / height), m
    height_m: float
    pins: list[tuple[int, int]] = field(default_factory=list)
    #: (-x face, +x face) node sets of a cube, for the lateral expansion
    sides: tuple[np.ndarray, np.ndarray] | None = None
    #: per pad (moved, held), the traction's coefficients (c0 N/m^2, cx N/m^3, cy N/m^3); None: displacements
    pad_weights: tuple[np.ndarray, np.ndarray] | None = None
    #: a grid mesh's integer grid coordinates per node (:func:`~msdgrasp.physics.mesh_gen.kuhn_lattice`); None: none
    lattice: np.ndarray | None = None

    @property
    def padded(self) -> bool:
        """Whether the case is loaded by the pads' forces (else by prescribed displacements)."""
        return self.pad_weights is not None

    def prescribed(self) -> np.ndarray:
        """Indices of the prescribed degrees of freedom (3 i + axis)."""
        comps = () if self.padded else (0, 1, 2) if self.bonded else (2,)
        dofs = [3 * np.concatenate([self.moved, self.held]) + c for c in comps]
        dofs += [np.array([3 * i + a]) for i, a in self.pins]
        return np.unique(np.concatenate(dofs))

    def unit_load(self) -> np.ndarray:
        """The pads' nodal forces (3N,), N: 1 N along -z on the moved pad, 1 N along +z on the held pad."""
        if not self.padded:
            raise ConfigError(f"case {self.name!r} is loaded by displacements, not by pads")
        f = np.zeros(3 * self.mesh.n_nodes)
        for nodes, coef, sign in ((self.moved, self.pad_weights[0], -1.0), (self.held, self.pad_weights[1], 1.0)):
            f[2::3] += sign * traction_nodal_forces(self.mesh, pad_faces(self.mesh, nodes), coef)
        return f

    def displacement_loaded(self) -> LoadCase:
        """The case itself; a pad-loaded one is refused (one line), where a caller prescribes the indenter's travel."""
        if self.padded:
            raise ConfigError(f"case {self.name!r} is loaded by its pads' forces, not by a travel: only the linear "
                              "comparison (unit_response) takes it")
        return self

    def targets(self, travel_m: float) -> np.ndarray:
        """Displacement (3N,) with the prescribed values at the prescribed dofs, m."""
        self.displacement_loaded()
        u = np.zeros(3 * self.mesh.n_nodes)
        u[3 * self.moved + 2] = -travel_m
        return u

    def force(self, f_ext: np.ndarray) -> float:
        """The indenter's push (N, > 0 in compression) from the external nodal forces (3N,) it exerts."""
        self.displacement_loaded()
        return float(-f_ext[3 * self.moved + 2].sum())


def pad_faces(mesh: TetMesh, nodes: np.ndarray) -> np.ndarray:
    """The surface faces (S, 3) whose three nodes are all in ``nodes``: a pad's loaded area. On a split mesh whose
    pad holds the midpoints between its nodes (:func:`refined_case`) these are exactly the split faces of the coarse
    pad's, the same area."""
    faces = boundary_faces(mesh.tets, mesh.name)
    inside = np.zeros(mesh.n_nodes, dtype=bool)
    inside[nodes] = True
    return faces[inside[faces].all(axis=1)]


def traction_nodal_forces(mesh: TetMesh, faces: np.ndarray, coef: Sequence[float]) -> np.ndarray:
    """Nodal forces (N,), N, of a traction w = c0 + cx x + cy y (N/m^2) over flat triangles ``faces``: the
    consistent (P1) load, exact for a linear w, f_a = A / 12 (2 w_a + w_b + w_c) on each face."""
    c0, cx, cy = coef
    p = mesh.nodes[faces]  # (S, 3 nodes, 3)
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    w = c0 + cx * p[:, :, 0] + cy * p[:, :, 1]
    out = np.zeros(mesh.n_nodes)
    np.add.at(out, faces.ravel(), (area[:, None] / 12.0 * (w + w.sum(axis=1, keepdims=True))).ravel())
    return out


def _balanced_pads(mesh: TetMesh, top: np.ndarray, bottom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Traction coefficients (c0, cx, cy) of two pads: uniform on ``top``, 1 N; linear on ``bottom``, 1 N with its
    resultant on the top's line of action, so the pair is in force and moment balance and the pins carry nothing."""
    def moments(nodes: np.ndarray, coef) -> np.ndarray:  # (force, x moment arm, y moment arm) of a traction
        f = traction_nodal_forces(mesh, pad_faces(mesh, nodes), coef)
        return np.array([f.sum(), f @ mesh.nodes[:, 0], f @ mesh.nodes[:, 1]])

    m_top = moments(top, (1.0, 0.0, 0.0))
    basis = np.stack([moments(bottom, e) for e in np.eye(3)], axis=1)
    if not m_top[0] > 0 or np.linalg.cond(basis) > 1e12:
        raise ConfigError(f"pads of {mesh.name!r}: each needs surface faces with all three nodes in it, not in a line")
    lower = np.linalg.solve(basis, m_top / m_top[0])
    w = lower[0] + mesh.nodes[bottom, :2] @ lower[1:]
    if not (w > 0).all():  # (a traction that pulls somewhere is no pad)
        raise ConfigError(f"pads of {mesh.name!r}: the upper pad's line of action falls outside the lower pad")
    return np.array([1.0 / m_top[0], 0.0, 0.0]), lower


def _rigid_pins(mesh: TetMesh, exclude: np.ndarray) -> list[tuple[int, int]]:
    """Six (node, axis) pins that remove a free body's rigid motions and nothing else (3-2-1), pad nodes excluded:
    the node a nearest the centroid holds x, y, z; the node b farthest from it along x holds y and z (the turns about
    z and y); the node c farthest in x-y from the line a-b holds z (the turn about that line). Three z pins in line
    would hold a deformation too."""
    keep = np.setdiff1d(np.arange(mesh.n_nodes), exclude)
    p = mesh.nodes[keep]
    a = int(np.argmin(np.linalg.norm(p - mesh.nodes.mean(axis=0), axis=1)))
    b = int(np.argmax(np.abs(p[:, 0] - p[a, 0])))
    ab, ap = p[b, :2] - p[a, :2], p[:, :2] - p[a, :2]
    c = int(np.argmax(np.abs(ab[0] * ap[:, 1] - ab[1] * ap[:, 0])))
    size = float(np.ptp(mesh.nodes, axis=0).max())
    if abs(ab[0]) <= 1e-9 * size or abs(ab[0] * ap[c, 1] - ab[1] * ap[c, 0]) <= 1e-9 * size**2:
        raise ConfigError(f"mesh {mesh.name!r}: no three nodes off the pads span x and y for the rigid-motion pins")
    a, b, c = (int(keep[i]) for i in (a, b, c))
    return [(a, 0), (a, 1), (a, 2), (b, 1), (b, 2), (c, 2)]


def _resolution_name(resolution: str) -> str:
    key = str(resolution).strip().lower()
    if key not in CUBE_CELLS:
        raise ConfigError(f"resolution = {resolution!r} is not allowed; choose one of {list(CUBE_CELLS)}")
    return key


def load_case(name: str, resolution: str = "coarse") -> LoadCase:
    """One of :data:`CASES` at a resolution (coarse, medium, fine)."""
    res = _resolution_name(resolution)
    if name.removesuffix("-j1") in ("cube", "cube-slip"):
        if name.endswith("-j1"):  # (an even number of cells per edge, so that the mirrored cells balance: 6 / 8 / 12)
            mesh = cube_mesh(CUBE_SIDE_M, CUBE_CELLS[res] + CUBE_CELLS[res] % 2, "alternating")
        else:
            mesh = cube_mesh(CUBE_SIDE_M, CUBE_CELLS[res])
        z = mesh.nodes[:, 2]
        tol = 1e-9 * CUBE_SIDE_M
        top = np.flatnonzero(z > z.max() - tol)
        bottom = np.flatnonzero(z < z.min() + tol)
        x = mesh.nodes[:, 0]
        sides = (np.flatnonzero(x < x.min() + tol), np.flatnonzero(x > x.max() - tol))
        pins: list[tuple[int, int]] = []
        if name.startswith("cube-slip"):
            # the bottom node nearest the axis holds x and y; the bottom node farthest along +x holds y (rotation)
            b = mesh.nodes[bottom]
            c = int(bottom[np.argmin(np.hypot(b[:, 0], b[:, 1]))])
            f = int(bottom[np.argmax(b[:, 0] - np.abs(b[:, 1]))])
            pins = [(c, 0), (c, 1), (f, 1)]
        return LoadCase(name, mesh, top, bottom, not name.startswith("cube-slip"), CUBE_SIDE_M, pins, sides,
                        lattice=kuhn_lattice((len(np.unique(x)) - 1,) * 3))
    body = name.removesuffix("-pad")
    if body == "sphere":
        mesh = sphere_even_mesh(0.05, res)
        radius = 0.5 * float(np.ptp(mesh.nodes[:, 2]))
        # the poles: the surface nodes within the punch radius of the z axis, on both faces
        moved, held = _patches(mesh, np.zeros(3), INDENTER_RADIUS_FRACTION * radius + 1e-12)
        height = 2.0 * radius
    elif body in ("spleen", "spleen-even", "spleen-j1"):
        grid = spleen_mesh(res)
        if body == "spleen":
            mesh = grid
        elif body == "spleen-j1":
            mesh = spleen_j1_mesh(res)
        else:
            mesh = spleen_even_mesh(res)
        # the middle of the long axis: the surface nodes nearest the x-y location of the grid's node centroid, on both
        # faces (spleen-even has the grid's surface: the same patches)
        moved, held = _patches(mesh, grid.nodes.mean(axis=0), SPLEEN_INDENTER_RADIUS_M)
        height = float(mesh.nodes[moved, 2].mean() - mesh.nodes[held, 2].mean())
    else:
        raise ConfigError(f"case = {name!r} is not allowed; choose one of {list(CASES)}")
    lattice = spleen_lattice(res) if body == "spleen-j1" else None
    if name == body:
        return LoadCase(name, mesh, moved, held, True, height, lattice=lattice)
    both = np.concatenate([moved, held])
    return LoadCase(name, mesh, moved, held, False, height, _rigid_pins(mesh, both),
                    pad_weights=_balanced_pads(mesh, moved, held), lattice=lattice)


def _patches(mesh: TetMesh, centre: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The surface nodes within ``radius_m`` of the vertical line through ``centre``, above it and below it."""
    surf = mesh.surface_nodes
    p = mesh.nodes[surf]
    near = np.hypot(p[:, 0] - centre[0], p[:, 1] - centre[1]) <= radius_m
    return surf[near & (p[:, 2] > centre[2])], surf[near & (p[:, 2] < centre[2])]


# =================================================================================================
# the finite-element reference (scikit-fem)
# =================================================================================================


def lame(youngs_modulus_pa: float, poisson: float) -> tuple[float, float]:
    """(lambda, mu) in Pa."""
    if not (-1.0 < poisson < 0.5):
        raise ConfigError(f"poisson = {poisson!r} must be in (-1, 0.5)")
    lam = youngs_modulus_pa * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return lam, youngs_modulus_pa / (2.0 * (1.0 + poisson))


def _skfem_mesh(mesh: TetMesh):
    """The project's mesh as scikit-fem's (the same nodes and tets, in order)."""
    return _skfem().MeshTet(np.ascontiguousarray(mesh.nodes.T), np.ascontiguousarray(mesh.tets.T))


def _elastic_system(m, order: int, youngs_modulus_pa: float, poisson: float):
    """(basis, stiffness matrix N/m in scikit-fem's dof order) of linear elasticity with P1 or P2 tets on mesh ``m``."""
    skfem = _skfem()
    from skfem.models.elasticity import linear_elasticity

    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1() if order == 1 else skfem.ElementTetP2()))
    return basis, skfem.asm(linear_elasticity(*lame(youngs_modulus_pa, poisson)), basis).tocsr()


def _basis(mesh: TetMesh):
    skfem = _skfem()
    basis = skfem.Basis(_skfem_mesh(mesh), skfem.ElementVector(skfem.ElementTetP1()))
    # the project numbers dof 3 i + axis; scikit-fem's own numbering is read from nodal_dofs (3, N)
    perm = np.asarray(basis.nodal_dofs).T.ravel()
    return basis, perm


def fem_stiffness(mesh: TetMesh, youngs_modulus_pa: float, poisson: float) -> sp.csr_matrix:
    """Linear-elastic P1 stiffness matrix (3N x 3N, N/m) in the project's dof order (3 i + axis)."""
    skfem = _skfem()
    from skfem.models.elasticity import linear_elasticity

    basis, perm = _basis(mesh)
    K = skfem.asm(linear_elasticity(*lame(youngs_modulus_pa, poisson)), basis).tocsr()
    return K[perm][:, perm].tocsr()


#: free dofs above which a nodal (3 i + axis) system is solved by conjugate gradients with smoothed-aggregation
#: multigrid (pyamg, in the extra ``fem``) instead of a sparse direct solve, whose fill-in outgrows memory on the fine
#: meshes split twice (~700k dofs); to a relative residual of :data:`AMG_TOLERANCE`
AMG_MIN_DOFS = 100_000
AMG_TOLERANCE = 1e-11


def _solve_prescribed(K: sp.spmatrix, presc: np.ndarray, u: np.ndarray, rhs: np.ndarray | None = None,
                      nodes: np.ndarray | None = None) -> np.ndarray:
    """u with its free dofs solving K u = rhs (0 by default) for the prescribed values it holds. ``nodes`` (N, 3):
    the system is nodal in the project's dof order, so a large one may go to multigrid with its rigid-body modes."""
    free = np.setdiff1d(np.arange(K.shape[0]), presc)
    K = K.tocsr()
    b = -(K[free][:, presc] @ u[presc]) + (0.0 if rhs is None else rhs[free])
    u = u.copy()
    A = K[free][:, free]
    if nodes is None or len(free) < AMG_MIN_DOFS:
        u[free] = spla.spsolve(A.tocsc(), b)
        return u
    with needs_extra("fem", "the finite-element reference on a large mesh (multigrid)"):
        import pyamg
    x, y, z = (np.asarray(nodes)[:, k] for k in range(3))
    modes = np.zeros((K.shape[0], 6))  # translations and rotations about x, y, z
    for k in range(3):
        modes[k::3, k] = 1.0
    modes[1::3, 3], modes[2::3, 3] = -z, y
    modes[0::3, 4], modes[2::3, 4] = z, -x
    modes[0::3, 5], modes[1::3, 5] = -y, x
    solver = pyamg.smoothed_aggregation_solver(A.tocsr(), B=modes[free], symmetry="symmetric", max_coarse=2000)
    residuals: list[float] = []
    u[free] = solver.solve(b, tol=AMG_TOLERANCE, accel="cg", maxiter=1000, residuals=residuals)
    if not residuals[-1] <= 10 * AMG_TOLERANCE * residuals[0]:
        raise RuntimeError(f"multigrid did not converge: relative residual {residuals[-1] / residuals[0]:.1e}")
    return u


def unit_response(K: sp.spmatrix, case: LoadCase) -> tuple[float, np.ndarray]:
    """A linear model's (stiffness matrix ``K``, N/m) response to the case: (force per unit travel N/m, displacement
    (3N,) at unit travel m). Displacement-loaded: the indenter's reaction to a unit travel. Pad-loaded: the pads'
    forces f (:meth:`LoadCase.unit_load`, 1 N on each pad) give u; the travel is the pads' approach f . u, per newton
    of squeeze."""
    if not case.padded:
        u1 = _solve_prescribed(K, case.prescribed(), case.targets(1.0), nodes=case.mesh.nodes)
        return case.force(K @ u1), u1
    f = case.unit_load()
    presc = case.prescribed()
    u = _solve_prescribed(K, presc, np.zeros(K.shape[0]), f, nodes=case.mesh.nodes)
    reaction = float(np.abs((K @ u)[presc]).max())
    if reaction > 1e-8:  # (1 N on each pad: a pin that carries load holds more than a rigid motion)
        raise RuntimeError(f"case {case.name!r}: a pin carries {reaction:.2e} N; the pads are not in balance")
    approach = float(f @ u)  # (f is self-equilibrated: the pins' rigid motion does no work on it)
    return 1.0 / approach, u / approach


def fem_linear_forces(case: LoadCase, youngs_modulus_pa: float, poisson: float,
                      strains: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Linear FEM: (indenter force N per strain, displacement (3N,) at unit travel m)."""
    k, u1 = unit_response(fem_stiffness(case.mesh, youngs_modulus_pa, poisson), case)
    return np.array([k * s * case.height_m for s in strains]), u1


def _edge_roles(case: LoadCase, m) -> tuple[np.ndarray, np.ndarray]:
    """scikit-fem mesh ``m``'s edges (2, E) of the case's mesh and each edge's role: 1 where both its nodes are moved,
    2 where both are held, else 0 (an edge prescribed alike keeps its midpoint with its nodes, as P1 implies)."""
    role = np.zeros(case.mesh.n_nodes, dtype=np.int64)
    role[case.moved], role[case.held] = 1, 2
    a, b = np.asarray(m.edges)
    return np.stack([a, b]), np.where(role[a] == role[b], role[a], 0)


def fem_quadratic_force(case: LoadCase, youngs_modulus_pa: float, poisson: float) -> float:
    """Linear FEM with quadratic (P2) tets on the case's tets: the indenter force per unit travel, N/m. An edge whose
    two nodes are prescribed alike (both moved or both held) has its midpoint prescribed with them, the constraint
    P1 implies along that edge; the force is the reaction on every moved dof. What the P1 reference's own
    discretisation costs on the same mesh."""
    mesh = case.displacement_loaded().mesh
    m = _skfem_mesh(mesh)
    basis, K = _elastic_system(m, 2, youngs_modulus_pa, poisson)
    nodal, edge = np.asarray(basis.nodal_dofs), np.asarray(basis.edge_dofs)
    _, role = _edge_roles(case, m)
    alike = role > 0
    comps = (0, 1, 2) if case.bonded else (2,)
    moved = np.concatenate([nodal[2, case.moved], edge[2, role == 1]])
    presc = [nodal[c, np.concatenate([case.moved, case.held])] for c in comps]
    presc += [edge[c, alike] for c in comps] + [np.array([nodal[axis, i]]) for i, axis in case.pins]
    u = np.zeros(K.shape[0])
    u[moved] = -1.0
    u = _solve_prescribed(K, np.unique(np.concatenate(presc)), u)
    return float(-(K @ u)[moved].sum())


def refined_case(case: LoadCase) -> LoadCase:
    """The case on its mesh split once (each tet into eight at its edges' midpoints, scikit-fem's refinement), with the
    same prescribed surface: a midpoint is moved or held where both ends of its edge are (the constraint P1 implies
    along that edge), so that the refinements solve one problem and their forces converge to its continuum value."""
    mesh = case.mesh
    m = _skfem_mesh(mesh)
    (a, b), role = _edge_roles(case, m)
    fine = m.refined()
    nodes, tets = np.asarray(fine.p).T.copy(), np.asarray(fine.t).T.copy()
    if not np.allclose(nodes[mesh.n_nodes:mesh.n_nodes + len(a)], 0.5 * (mesh.nodes[a] + mesh.nodes[b])):
        raise RuntimeError("scikit-fem's refinement no longer numbers the new nodes by edge")
    flip = tet_signed_volumes(nodes, tets) < 0  # (the refinement does not keep the tets' orientation)
    tets[flip, 1], tets[flip, 2] = tets[flip, 2], tets[flip, 1].copy()
    mid = mesh.n_nodes + np.arange(len(a))  # (edge e's midpoint is node n_nodes + e)
    return dataclasses.replace(case, mesh=TetMesh(nodes, tets, name=f"{mesh.name}-split"),
                               moved=np.concatenate([case.moved, mid[role == 1]]),
                               held=np.concatenate([case.held, mid[role == 2]]), sides=None, lattice=None)


def converged_linear_force(case: LoadCase, youngs_modulus_pa: float, poisson: float, splits: int = 2,
                           rate: float | None = None) -> dict:
    """The linear FEM's force per unit travel (N/m) on the case's mesh and ``splits`` uniform refinements of it (P1),
    and its limit by Richardson extrapolation from the last two at the convergence ``rate`` (error ~ h^rate); without
    a rate, the rate fitted from the last three (``splits`` >= 2). A bonded punch's rim is singular: the rate is near
    1, not P1's 2 of a smooth solution. Each split has eight times the tets."""
    if splits < (2 if rate is None else 1):
        raise ConfigError(f"splits = {splits!r} must be >= 2 without a rate (three levels fit it), >= 1 with one")
    forces, levels = [], case
    for level in range(splits + 1):
        k, _ = fem_linear_forces(levels, youngs_modulus_pa, poisson, [1.0 / levels.height_m])
        forces.append(float(k[0]))
        if level < splits:
            levels = refined_case(levels)
    if rate is None:
        f0, f1, f2 = forces[-3:]
        ratio = (f0 - f1) / (f1 - f2) if f1 != f2 else math.inf
        rate = math.log2(ratio) if 1.0 < ratio < math.inf else math.nan
    limit = forces[-1] - (forces[-2] - forces[-1]) / (2.0**rate - 1.0) if rate > 0 else math.nan
    return {"p1_N_per_m": forces, "nodes": levels.mesh.n_nodes, "rate": rate, "limit_N_per_m": limit}


def _neo_hookean_forms(lam: float, mu: float):
    skfem = _skfem()
    from skfem.helpers import ddot, det, grad, inv, mul, trace, transpose

    def kinematics(w):
        G = grad(w["u"])
        F = G.copy()
        for a in range(3):
            F[a, a] += 1.0
        J = det(F)
        Finv = inv(F)
        return F, J, Finv, transpose(Finv)

    @skfem.LinearForm
    def residual(v, w):
        F, J, _, FiT = kinematics(w)
        P = mu * (F - FiT) + lam * np.log(J) * FiT  # first Piola-Kirchhoff stress
        return ddot(P, grad(v))

    @skfem.BilinearForm
    def tangent(u, v, w):
        F, J, Finv, FiT = kinematics(w)
        dF = grad(u)
        dP = (mu * dF + (mu - lam * np.log(J)) * mul(FiT, mul(transpose(dF), FiT))
              + lam * trace(mul(Finv, dF)) * FiT)
        return ddot(dP, grad(v))

    return residual, tangent


def fem_neo_hookean_forces(case: LoadCase, youngs_modulus_pa: float, poisson: float, strains: Sequence[float],
                           increments_per_strain: float = 50.0, tol: float = 1e-9,
                           max_newton: int = 30) -> np.ndarray:
    """Compressible neo-Hookean FEM (Lame constants from E, nu: the same small-strain limit as the linear one):
    the indenter force (N) at each strain, loaded in increments with Newton's method at each."""
    skfem = _skfem()
    basis, perm = _basis(case.mesh)
    residual, tangent = _neo_hookean_forms(*lame(youngs_modulus_pa, poisson))
    n = 3 * case.mesh.n_nodes
    presc = case.prescribed()
    free = np.setdiff1d(np.arange(n), presc)
    inv_perm = np.empty_like(perm)
    inv_perm[perm] = np.arange(n)
    u = np.zeros(n)  # the project's dof order
    nodes, tets = case.mesh.nodes, case.mesh.tets

    def positive(v: np.ndarray) -> bool:  # no tet inverted (ln J undefined)
        return bool(np.all(tet_signed_volumes(nodes + v.reshape(-1, 3), tets) > 0.0))

    def residual_of(v: np.ndarray) -> np.ndarray:
        return skfem.asm(residual, basis, u=basis.interpolate(v[inv_perm]))[perm]

    out = []
    done = 0.0
    last_step = np.zeros(n)
    for s in sorted(strains):
        steps = max(1, int(math.ceil((s - done) * increments_per_strain)))
        for level in np.linspace(done, s, steps + 1)[1:]:
            target = case.targets(level * case.height_m)
            u_prev = u.copy()
            # start from the last increment's motion (the path is smooth): the free nodes move with the indenter
            trial = u + last_step
            trial[presc] = target[presc]
            if not positive(trial):
                trial = u.copy()
                trial[presc] = target[presc]
            u = trial
            scale = None
            R = residual_of(u)
            for _ in range(max_newton):
                scale = scale or max(float(np.abs(R[presc]).max()), 1e-30)
                if float(np.abs(R[free]).max()) <= tol * scale:
                    break
                K = skfem.asm(tangent, basis, u=basis.interpolate(u[inv_perm])).tocsr()[perm][:, perm].tocsr()
                du = spla.spsolve(K[free][:, free].tocsc(), -R[free])
                # backtrack until no tet inverts and the residual falls (a few halvings at most)
                step, r0 = 1.0, float(np.linalg.norm(R[free]))
                for _ls in range(12):
                    trial = u.copy()
                    trial[free] += step * du
                    if positive(trial):
                        R_trial = residual_of(trial)
                        if float(np.linalg.norm(R_trial[free])) < r0 or _ls >= 8:
                            break
                    step *= 0.5
                else:
                    raise RuntimeError(f"neo-Hookean FEM: no admissible Newton step at strain {level:.3f} "
                                       f"({case.name})")
                u, R = trial, R_trial
            else:
                raise RuntimeError(f"neo-Hookean FEM: Newton did not converge at strain {level:.3f} ({case.name})")
            last_step = u - u_prev
        done = s
        w = basis.interpolate(u[inv_perm])
        out.append(case.force(skfem.asm(residual, basis, u=w)[perm]))
    order = np.argsort(np.argsort(strains))
    return np.asarray(out)[order]


# =================================================================================================
# the MSD at equilibrium
# =================================================================================================


def msd_model(mesh: TetMesh, params: TissueParams, **overrides) -> TissueModel:
    """The tissue on ``mesh`` without gravity (the comparison is of the elastic response alone)."""
    data = {**to_dict(params), "gravity_m_per_s2": (0.0, 0.0, 0.0), **overrides}
    return TissueModel.from_params(mesh, from_dict(TissueParams, data, where="fem"))


def _internal(model: TissueModel, x: np.ndarray) -> np.ndarray:
    """Spring plus volume-barrier forces on each node (N, 3), N: the kernel's force law at rest (no velocity)."""
    f = model.internal_forces(x)
    if model.kvol.size:
        volume_forces(np.ascontiguousarray(x), model.tets, model.rest_volume, model.kvol, model.volume_threshold,
                      1.0, f)
    return f


def _tangent(model: TissueModel, x: np.ndarray, convex: bool = False) -> sp.csr_matrix:
    """Tangent stiffness (3N x 3N) of the springs at ``x`` (material + geometric terms) plus the Gauss-Newton part
    of the volume barrier (positive semi-definite; Newton's line search makes up for the rest)."""
    e = model.edges
    d = x[e[:, 1]] - x[e[:, 0]]
    length = np.linalg.norm(d, axis=1)
    nrm = d / length[:, None]
    dl = length - model.rest_length
    tension = numpy_spring_law(dl, model.k1, model.k2, model.dlc)
    slope = model.k1 + 3.0 * model.k2 * np.minimum(np.abs(dl), model.dlc) ** 2
    nn = nrm[:, :, None] * nrm[:, None, :]
    # (a compressed spring's geometric stiffness is negative: kept for Newton, dropped by ``convex`` where the full
    # tangent is indefinite and its step does not descend)
    if convex:
        tension = np.maximum(tension, 0.0)
    blocks = slope[:, None, None] * nn + (tension / length)[:, None, None] * (np.eye(3)[None] - nn)
    n3 = 3 * model.n_nodes
    K = assemble_edge_blocks(blocks, e, model.n_nodes)
    if model.kvol.size:
        t = model.tets
        p0 = x[t[:, 0]]
        e1, e2, e3 = x[t[:, 1]] - p0, x[t[:, 2]] - p0, x[t[:, 3]] - p0
        vol = np.einsum("ij,ij->i", e1, np.cross(e2, e3)) / 6.0
        jac = vol / model.rest_volume
        _, d2 = numpy_barrier_slopes(jac, model.volume_threshold)
        act = np.flatnonzero(d2 > 0)
        if act.size:
            g1 = np.cross(e2[act], e3[act]) / 6.0
            g2 = np.cross(e3[act], e1[act]) / 6.0
            g3 = np.cross(e1[act], e2[act]) / 6.0
            g = np.stack([-(g1 + g2 + g3), g1, g2, g3], axis=1).reshape(len(act), 12)  # dV/dx of the 4 nodes
            w = model.kvol[act] * d2[act] / model.rest_volume[act]  # k V0 psi'' (dJ/dV)^2
            dofs = (3 * t[act][:, :, None] + np.arange(3)[None, None, :]).reshape(len(act), 12)
            r = np.repeat(dofs, 12, axis=1).ravel()
            c = np.tile(dofs, (1, 12)).ravel()
            v = (w[:, None, None] * g[:, :, None] * g[:, None, :]).ravel()
            K = K + sp.csr_matrix((v, (r, c)), shape=(n3, n3))
    return K


def msd_forces(case: LoadCase, model: TissueModel, strains: Sequence[float], increments_per_strain: float = 50.0,
               tol: float = 1e-8, max_newton: int = 60) -> tuple[np.ndarray, list[np.ndarray]]:
    """The network's equilibrium at each strain (loaded in increments, Newton with a backtracking line search on
    the elastic energy): (indenter force N per strain, node positions (N, 3) per strain). A strain at or beyond
    an increment without an equilibrium (Newton stalls where the force has peaked) gets NaN."""
    x0 = model.rest_positions
    n = 3 * model.n_nodes
    presc = case.prescribed()
    free = np.setdiff1d(np.arange(n), presc)
    x = x0.copy().ravel()
    forces, shapes = {}, {}
    done = 0.0
    for s in sorted(strains):
        steps = max(1, int(math.ceil((s - done) * increments_per_strain)))
        for level in np.linspace(done, s, steps + 1)[1:]:
            x[presc] = x0.ravel()[presc] + case.targets(level * case.height_m)[presc]
            scale = None
            for _ in range(max_newton):
                f = _internal(model, x.reshape(-1, 3)).ravel()
                scale = scale or max(float(np.abs(f[presc]).max()), 1e-30)
                if float(np.abs(f[free]).max()) <= tol * scale:
                    break
                e0 = model.elastic_energy(x.reshape(-1, 3))
                for convex in (False, True):
                    K = _tangent(model, x.reshape(-1, 3), convex)
                    dx = spla.spsolve(K[free][:, free].tocsc(), f[free])
                    slope = float(f[free] @ dx)  # the energy's decrease per unit step along dx
                    if not slope > 0.0:
                        continue
                    step = 1.0
                    for _ls in range(40):
                        trial = x.copy()
                        trial[free] += step * dx
                        # (Armijo, with a round-off allowance: near convergence the energy's decrease is below
                        # its float precision, and a strict test would stall Newton one step short of the tolerance)
                        if model.elastic_energy(trial.reshape(-1, 3)) <= e0 - 1e-4 * step * slope + 1e-12 * abs(e0):
                            break
                        step *= 0.5
                    else:
                        continue
                    break
                else:
                    trial = x  # no descent left: round-off level, the tolerance check decides
                x = trial
            else:
                # no equilibrium on the loading path (the network's force has peaked: a limit point, past which a
                # quasi-static path does not exist); this and every larger strain are NaN
                for rest in strains:
                    if rest >= s:
                        forces[rest], shapes[rest] = math.nan, x.reshape(-1, 3).copy()
                return np.array([forces[q] for q in strains]), [shapes[q] for q in strains]
        done = s
        f = _internal(model, x.reshape(-1, 3)).ravel()
        forces[s] = case.force(-f)  # the indenter balances the internal forces at the moved nodes
        shapes[s] = x.reshape(-1, 3).copy()
    return np.array([forces[s] for s in strains]), [shapes[s] for s in strains]


def msd_linear_force(case: LoadCase, model: TissueModel) -> tuple[float, np.ndarray]:
    """The linearised network (springs at rest, K1 only): (indenter force per metre of travel N/m, u (3N,) at unit
    travel)."""
    from ..physics.tissue import stiffness_matrix

    return unit_response(stiffness_matrix(model.rest_positions, model.edges, model.k1), case)


def poisson_ratio(case: LoadCase, u_unit: np.ndarray) -> float:
    """Effective Poisson ratio of a cube between frictionless plates: the lateral strain (mean x displacement of the
    +x face minus the -x face's, over the edge) over the axial strain, from the displacement at unit travel."""
    if case.sides is None:
        raise ConfigError(f"case {case.name!r} has no lateral faces to measure")
    lo, hi = case.sides
    ux = u_unit[0::3]
    lateral = (ux[hi].mean() - ux[lo].mean()) / case.height_m
    axial = -1.0 / case.height_m
    return float(-lateral / axial)


# =================================================================================================
# closed-form checks of the FEM solver
# =================================================================================================


def bar_check(youngs_modulus_pa: float = 12e3, poisson: float = 0.45, resolution: str = "coarse") -> dict:
    """A prism between frictionless plates (uniaxial stress): the linear FEM's axial stiffness against E A / L."""
    case = load_case("cube-slip", resolution)
    k, _ = fem_linear_forces(case, youngs_modulus_pa, poisson, [1.0 / case.height_m])
    exact = youngs_modulus_pa * CUBE_SIDE_M**2 / CUBE_SIDE_M
    return {"check": "bar axial stiffness E A / L (linear FEM, frictionless plates)", "fem_N_per_m": float(k[0]),
            "closed_form_N_per_m": exact, "rel_error": float(k[0] / exact - 1.0)}


def confined_check(youngs_modulus_pa: float = 12e3, poisson: float = 0.45, resolution: str = "coarse") -> dict:
    """The prism with its sides held laterally (confined compression, uniaxial strain): the linear FEM's stiffness
    against (lambda + 2 mu) A / L (this one sees the Poisson ratio, the bar's does not)."""
    case = load_case("cube-slip", resolution)
    mesh = case.mesh
    tol = 1e-9 * CUBE_SIDE_M
    walls = [np.flatnonzero(np.abs(mesh.nodes[:, a]) > 0.5 * CUBE_SIDE_M - tol) for a in (0, 1)]
    case.pins = [(int(i), 0) for i in walls[0]] + [(int(i), 1) for i in walls[1]]
    k, _ = fem_linear_forces(case, youngs_modulus_pa, poisson, [1.0 / case.height_m])
    lam, mu = lame(youngs_modulus_pa, poisson)
    exact = (lam + 2.0 * mu) * CUBE_SIDE_M
    return {"check": "confined compression (lambda + 2 mu) A / L (linear FEM)", "fem_N_per_m": float(k[0]),
            "closed_form_N_per_m": exact, "rel_error": float(k[0] / exact - 1.0)}


def neo_hookean_uniaxial_force(youngs_modulus_pa: float, poisson: float, stretch: float, area_m2: float) -> float:
    """Closed form: the compressive force (N) on a compressible neo-Hookean prism in uniaxial stress at axial stretch
    ``stretch`` (< 1): the lateral stretch l solves mu (l - 1/l) + lambda ln(s l^2) / l = 0, then the nominal
    stress is P = mu (s - 1/s) + lambda ln(s l^2) / s."""
    from scipy.optimize import brentq

    lam, mu = lame(youngs_modulus_pa, poisson)
    lat = brentq(lambda q: mu * (q - 1.0 / q) + lam * math.log(stretch * q * q) / q, 1.0, 3.0)
    return float(-(mu * (stretch - 1.0 / stretch) + lam * math.log(stretch * lat * lat) / stretch) * area_m2)


def neo_hookean_bar_check(youngs_modulus_pa: float = 12e3, poisson: float = 0.45, strain: float = 0.2) -> dict:
    """The neo-Hookean FEM on the cube between frictionless plates against :func:`neo_hookean_uniaxial_force`."""
    case = load_case("cube-slip", "coarse")
    f = fem_neo_hookean_forces(case, youngs_modulus_pa, poisson, [strain], increments_per_strain=25.0)[0]
    exact = neo_hookean_uniaxial_force(youngs_modulus_pa, poisson, 1.0 - strain, CUBE_SIDE_M**2)
    return {"check": f"neo-Hookean uniaxial stress at {strain:.0%} compression (closed form)", "fem_N": float(f),
            "closed_form_N": exact, "rel_error": float(f / exact - 1.0)}


def _plate_contact_force(K: sp.csr_matrix, zdofs: np.ndarray, z: np.ndarray, pins: np.ndarray, depth: float,
                         max_iter: int = 60) -> float:
    """Linear body (stiffness K) squeezed between frictionless rigid plates normal to z by a total travel ``depth``:
    active-set unilateral contact on the surface's z dofs ``zdofs`` at heights ``z`` (m); ``pins`` hold the free
    in-plane rigid motions (statically: they carry no load, as in
    :func:`~msdgrasp.physics.tissue.plate_compression_force`). Returns the top plate's force, N."""
    zmin, zmax = float(z.min()), float(z.max())
    tol = 1e-9 * (zmax - zmin)
    top = z >= zmax - 0.5 * depth - tol
    bot = z <= zmin + 0.5 * depth + tol
    for _ in range(max_iter):
        cons = top | bot
        presc = np.unique(np.concatenate([zdofs[cons], pins]))
        u = np.zeros(K.shape[0])
        u[zdofs[cons]] = np.where(top[cons], zmax - depth, zmin) - z[cons]
        u = _solve_prescribed(K, presc, u)
        r = (K @ u)[zdofs]
        zn = z + u[zdofs]
        ftol = 1e-9 * float(np.max(np.abs(r)))
        rel_t, rel_b = top & (r > ftol), bot & (r < -ftol)
        add_t = ~top & (zn > zmax - depth + tol)
        add_b = ~bot & (zn < zmin - tol)
        if not (rel_t.any() or rel_b.any() or add_t.any() or add_b.any()):
            return float(-r[top].sum())
        top, bot = (top & ~rel_t) | add_t, (bot & ~rel_b) | add_b
    raise RuntimeError("FEM plate contact: the active set did not converge")


def sphere_plate_force(mesh: TetMesh, youngs_modulus_pa: float, poisson: float, depth_m: float,
                       order: int = 1) -> float:
    """Linear FEM (P1 or P2 tets on the mesh's tets) of the body between frictionless plates: the plate force, N."""
    basis, K = _elastic_system(_skfem_mesh(mesh), order, youngs_modulus_pa, poisson)
    zdofs = np.asarray(basis.get_dofs().all("u^3"))
    z = basis.doflocs[2, zdofs]
    centre = mesh.nodes.mean(axis=0)
    pc = int(np.argmin(np.linalg.norm(mesh.nodes - centre, axis=1)))
    pf = int(np.argmax(np.abs(mesh.nodes[:, 0] - centre[0])))
    nd = np.asarray(basis.nodal_dofs)
    pins = np.array([nd[0, pc], nd[1, pc], nd[1, pf]])
    return _plate_contact_force(K, zdofs, z, pins, depth_m)


def hertz_check(youngs_modulus_pa: float = 12e3, poisson: float = 0.25, deformation: float = 0.10,
                resolutions: Sequence[str] = ("coarse", "medium", "fine"), order: int = 1) -> dict:
    """The linear FEM sphere between frictionless plates against Hertz at ``deformation`` x the diameter, per mesh,
    and the Richardson extrapolation of the two finest to zero element size (error ~ h^2, h ~ N^(-1/3)). Unlike the
    prism checks this one involves contact, which constant-strain tets resolve poorly: it is reported, and the
    comparison with the MSD uses the bonded (contact-free) load cases."""
    out = {"check": f"Hertz sphere between frictionless plates at {deformation:.0%} (linear FEM)", "meshes": {}}
    forces, sizes = [], []
    for res in resolutions:
        mesh = sphere_even_mesh(0.05, res)
        height = float(np.ptp(mesh.nodes[:, 2]))
        f = sphere_plate_force(mesh, youngs_modulus_pa, poisson, deformation * height, order)
        exact = hertz_sphere_force(youngs_modulus_pa, 0.5 * height, deformation * height, poisson)
        out["meshes"][res] = {"nodes": mesh.n_nodes, "fem_N": f, "hertz_N": exact, "rel_error": f / exact - 1.0}
        forces.append(f)
        sizes.append(mesh.n_nodes ** (-1.0 / 3.0))
    (fa, fb), (ha, hb) = forces[-2:], sizes[-2:]
    extrapolated = fb + (fb - fa) * hb**2 / (ha**2 - hb**2)
    out["extrapolated_N"] = extrapolated
    out["hertz_N"] = exact
    out["rel_error"] = extrapolated / exact - 1.0
    return out


# =================================================================================================
# calibrations of the springs
# =================================================================================================

#: the spring derivations compared (``calibrated``: van Gelder times one factor fitted per mesh to the linear FEM's
#: force on the bonded cube; ``fem-fit``: per tet, the six springs whose stiffness matrix is nearest the P1 element's
#: in the Frobenius norm; ``grid``: van Gelder reweighted by edge family, :func:`grid_springs`)
DERIVATIONS = ("van_gelder", "lloyd", "calibrated", "fem-fit", "grid")

#: :func:`grid_springs`' weights on van Gelder's per-tet share E V / L^2: a Kuhn tet's three grid-axis edges, its
#: two face diagonals and its body diagonal. Under a uniform strain the Kuhn grid's network, mirrored cells in equal
#: numbers, is a cubic crystal with C11 = E (a + 4 d / 9), C12 = C44 = 5 E d / 18 (axis edges of stiffness a E h,
#: diagonals d E h / 3 per cell of edge h); isotropy with the input E (nu = 1/4: C11 = 1.2 E, C44 = 0.4 E) needs
#: d = 1.44, a = 0.56. Van Gelder is a = d = 1: C11 = 1.444 E, C44 = 0.278 E, stiff along the axes, soft in shear.
GRID_AXIS_WEIGHT = 0.56
GRID_DIAGONAL_WEIGHT = 1.44


def grid_springs(mesh: TetMesh, youngs_modulus_pa: float, lattice: np.ndarray | None = None) -> np.ndarray:
    """Spring stiffnesses K1 (N/m, one per mesh edge) for a Kuhn grid: van Gelder's E V / L^2 per tet, times
    :data:`GRID_AXIS_WEIGHT` on each tet's three grid-axis edges and :data:`GRID_DIAGONAL_WEIGHT` on the other three.
    The family is read from the nodes' integer grid coordinates ``lattice`` (N, 3; an axis edge differs in one), or
    without them from the edge lengths (the three shortest), which is exact on an unmapped grid (a cube) only: on the
    mapped built-in meshes the lengths no longer tell the families apart, and on an unstructured mesh there is no
    family. On the alternating (J1) grid with an even number of cells per axis every interior node is a centre of
    symmetry, so a uniform strain is the network's equilibrium and the weights make it the isotropic solid; on the
    octant grid each octant's diagonals all lean one way (a coupling of shear and normal strain no positive spring
    removes), and it relaxes non-affinely."""
    x = mesh.nodes[mesh.tets]
    d2 = np.stack([((x[:, b] - x[:, a]) ** 2).sum(axis=1) for a, b in TET_EDGES], axis=1)
    if lattice is None:
        axis = np.argsort(np.argsort(d2, axis=1, kind="stable"), axis=1) < 3
    else:
        g = np.asarray(lattice)
        if g.shape != (mesh.n_nodes, 3):
            raise ValueError(f"lattice has shape {g.shape}, must be ({mesh.n_nodes}, 3): a node's three grid indices")
        g = g[mesh.tets]
        axis = np.stack([(g[:, b] != g[:, a]).sum(axis=1) == 1 for a, b in TET_EDGES], axis=1)
    vol = np.abs(tet_signed_volumes(mesh.nodes, mesh.tets))
    return _edge_sums(mesh, youngs_modulus_pa * vol[:, None] / d2 * np.where(axis, GRID_AXIS_WEIGHT,
                                                                              GRID_DIAGONAL_WEIGHT))


def _edge_sums(mesh: TetMesh, shares: np.ndarray) -> np.ndarray:
    """Per mesh edge, the sum of the tets' shares (T, 6) in :data:`~msdgrasp.physics.tissue.TET_EDGES` order over the
    tets that hold it, as van Gelder's rule sums them."""
    idx = edge_index(mesh.edges, mesh.n_nodes, mesh.tets[:, TET_EDGES[:, 0]].ravel(),
                     mesh.tets[:, TET_EDGES[:, 1]].ravel())
    k1 = np.zeros(len(mesh.edges))
    np.add.at(k1, idx, shares.ravel())
    return k1


def fem_fit_springs(mesh: TetMesh, youngs_modulus_pa: float, poisson: float = 0.25) -> np.ndarray:
    """Spring stiffnesses K1 (N/m, one per mesh edge) fitted tet by tet: the six springs of each tet whose summed
    k n n^T blocks are nearest (least squares over the 12 x 12 entries) the linear P1 element matrix
    V B^T D B; negative fits (a spring cannot push when stretched) are clipped to zero; summed over the tets that
    share an edge, as van Gelder's rule is."""
    x = mesh.nodes[mesh.tets]  # (T, 4, 3)
    lam, mu = lame(youngs_modulus_pa, poisson)
    J = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=1)  # rows: edge vectors
    vol = np.abs(np.linalg.det(J)) / 6.0
    Jinv = np.linalg.inv(J)  # grad of barycentric coords 1..3 are the columns of J^-T
    g = np.empty((len(x), 4, 3))
    g[:, 1:] = np.transpose(Jinv, (0, 2, 1))
    g[:, 0] = -g[:, 1:].sum(axis=1)
    eye = np.eye(3)
    # K[a i, b j] = V (lam g_ai g_bj + mu g_aj g_bi + mu delta_ij g_a . g_b)
    Ke = vol[:, None, None, None, None] * (
        lam * np.einsum("tai,tbj->taibj", g, g) + mu * np.einsum("taj,tbi->taibj", g, g)
        + mu * np.einsum("ij,tab->taibj", eye, np.einsum("tak,tbk->tab", g, g)))
    Ke = Ke.reshape(len(x), 12, 12)
    B = np.zeros((len(x), 6, 4, 3, 4, 3))
    for e, (a, b) in enumerate(TET_EDGES):
        d = x[:, b] - x[:, a]
        n = d / np.linalg.norm(d, axis=1, keepdims=True)
        nn = n[:, :, None] * n[:, None, :]
        B[:, e, a, :, a, :] = nn
        B[:, e, b, :, b, :] = nn
        B[:, e, a, :, b, :] = -nn
        B[:, e, b, :, a, :] = -nn
    B = B.reshape(len(x), 6, 144)
    G = np.einsum("tam,tbm->tab", B, B)
    h = np.einsum("tam,tm->ta", B, Ke.reshape(len(x), 144))
    return _edge_sums(mesh, np.clip(np.linalg.solve(G, h[..., None])[..., 0], 0.0, None))


def with_springs(model: TissueModel, k1: np.ndarray) -> TissueModel:
    """``model`` with other linear spring stiffnesses K1 (N/m); K2, the Maxwell branch and the dashpots follow them
    as :meth:`TissueModel.from_params` derives them from K1."""
    import dataclasses

    p = model.params
    return dataclasses.replace(model, k1=k1, k2=p.stiffening * k1 / model.rest_length**2,
                               kv=p.relaxation_strength * k1, cdash=p.spring_damping_time_s * k1)


# =================================================================================================
# the comparison
# =================================================================================================


def boussinesq_displacement(force_n: float, youngs_modulus_pa: float, poisson: float, points: np.ndarray) -> np.ndarray:
    """Displacement (3, n), m, at ``points`` (3, n; the solid is z <= 0) of a linear half-space under a normal point
    force ``force_n`` (N) pressing down at the origin (Boussinesq; Johnson, Contact Mechanics, eq. 3.19)."""
    g = youngs_modulus_pa / (2.0 * (1.0 + poisson))
    depth = -points[2]
    r = np.hypot(points[0], points[1])
    rho = np.sqrt(r * r + depth * depth)
    c = force_n / (4.0 * math.pi * g)
    u_r = c * (r * depth / rho**3 - (1.0 - 2.0 * poisson) * r / (rho * (rho + depth)))
    u_down = c * (depth**2 / rho**3 + 2.0 * (1.0 - poisson) / rho)
    safe = np.where(r > 0, r, 1.0)
    return np.array([u_r * points[0] / safe, u_r * points[1] / safe, -u_down])


def _graded_axis(first_m: float, ratio: float, length_m: float) -> np.ndarray:
    """Grid coordinates 0 .. ``length_m`` whose spacing starts at about ``first_m`` and grows by ``ratio``."""
    x = [0.0]
    h = first_m
    while x[-1] < length_m:
        x.append(x[-1] + h)
        h *= ratio
    return np.asarray(x) * (length_m / x[-1])


@dataclass
class HalfSpaceHertz:
    """A rigid sphere pressed into an elastic half-space (SI units; lengths relative to Hertz's contact radius a)."""

    #: the sphere's radius, m
    radius_m: float = 0.025
    #: Hertz's contact radius a of the load, m (the indentation is a^2 / R)
    contact_radius_m: float = 0.002
    #: element order of the check (2: quadratic tets; 1: the comparison's linear tets)
    order: int = 2
    #: grid cells across a near the contact
    cells_per_contact_radius: float = 4.0
    #: growth of the grid spacing away from the contact
    grading: float = 1.3
    #: the modelled quarter block's edge over a (its far faces carry Boussinesq's displacements)
    extent: float = 10.0


def halfspace_hertz_force(youngs_modulus_pa: float, poisson: float, setup: HalfSpaceHertz = HalfSpaceHertz()) -> dict:
    """The linear FEM of a frictionless rigid sphere (a paraboloid, as Hertz assumes) indenting a half-space by
    a^2 / R. A quarter block (symmetry planes x = 0 and y = 0) on a tensor grid graded toward the contact; its far
    faces carry the displacements of a point force equal to the contact force (Boussinesq; the block's truncation
    error falls as (a / extent)^2 instead of a / extent), iterated to a fixed point. The surface's z dofs within 2 a
    of the axis are condensed (one factorisation) and solved by an active set: a dof is in contact where it would
    penetrate, released where its contact force would pull. Returns the FEM's and Hertz's forces, N."""
    a, R = setup.contact_radius_m, setup.radius_m
    depth, side = a * a / R, setup.extent * a
    g = _graded_axis(a / setup.cells_per_contact_radius, setup.grading, side)
    basis, K = _elastic_system(_skfem().MeshTet.init_tensor(g, g, -g[::-1]), setup.order, youngs_modulus_pa, poisson)
    X, tol = basis.doflocs, 1e-9 * side
    comp = [np.asarray(basis.get_dofs().all(f"u^{i}")) for i in (1, 2, 3)]
    symmetric = np.concatenate([comp[0][np.abs(X[0, comp[0]]) < tol], comp[1][np.abs(X[1, comp[1]]) < tol]])
    far = np.setdiff1d(np.concatenate([c[(X[0, c] > side - tol) | (X[1, c] > side - tol) | (X[2, c] < tol - side)]
                                       for c in comp]), symmetric)
    axis = np.zeros(K.shape[0], dtype=np.int64)
    for i, c in enumerate(comp):
        axis[c] = i
    surface = comp[2][np.abs(X[2, comp[2]]) < tol]
    r = np.hypot(X[0, surface], X[1, surface])
    cand, rc = surface[r < 2.0 * a], r[r < 2.0 * a]
    free = np.setdiff1d(np.arange(K.shape[0]), np.concatenate([symmetric, cand, far]))
    lu = spla.splu(K[free][:, free].tocsc())
    K_c, K_f = K[cand], K[free]
    K_fc = K_f[:, cand].toarray()
    S = K_c[:, cand].toarray() - K_fc.T @ lu.solve(K_fc)  # the candidates' condensed stiffness, N/m
    K_c_far, K_c_free, K_f_far = K_c[:, far], K_c[:, free], K_f[:, far]
    target = -depth + rc**2 / (2.0 * R)  # the sphere's surface over each candidate, m
    exact = 4.0 / 3.0 * youngs_modulus_pa / (1.0 - poisson**2) * math.sqrt(R) * depth**1.5
    force, active = exact, rc < 0.7 * a
    for _ in range(30):
        u_far = np.zeros(K.shape[0])
        u_far[far] = boussinesq_displacement(force, youngs_modulus_pa, poisson, X[:, far])[axis[far],
                                                                                         np.arange(len(far))]
        load = K_c_far @ u_far[far] - K_c_free @ lu.solve(K_f_far @ u_far[far])
        for _ in range(100):
            u = np.where(active, target, 0.0)
            off = ~active
            if off.any():
                u[off] = np.linalg.solve(S[np.ix_(off, off)], -S[np.ix_(off, active)] @ u[active] - load[off])
            f = S @ u + load
            release, add = active & (f > 0.0), off & (u > target)
            if not (release.any() or add.any()):
                break
            active = (active & ~release) | add
        else:
            raise RuntimeError("half-space Hertz: the active set did not converge")
        new = -4.0 * float(f[active].sum())
        if abs(new - force) <= 1e-9 * exact:
            break
        force = new
    else:
        raise RuntimeError("half-space Hertz: the far field's force did not settle")
    return {"fem_N": new, "hertz_N": exact, "rel_error": new / exact - 1.0, "dofs": int(K.shape[0]),
            "contact_radius_rel": float(rc[active].max() / a)}


def halfspace_hertz_check(youngs_modulus_pa: float = 12e3, poisson: float = 0.25,
                          setup: HalfSpaceHertz = HalfSpaceHertz()) -> dict:
    """Hertz's force of a rigid sphere on a half-space against the FEM of :func:`halfspace_hertz_force`."""
    out = halfspace_hertz_force(youngs_modulus_pa, poisson, setup)
    return {"check": f"Hertz, rigid sphere on a half-space (linear FEM, P{setup.order} tets, contact)", **out}


@dataclass
class ComparisonSettings:
    """What :func:`compare` runs (SI units; strains as fractions of the case's height)."""

    cases: tuple[str, ...] = CASES
    resolutions: tuple[str, ...] = ("coarse", "fine")
    #: the continuum's Poisson ratio (0.25: the network's own)
    poisson: float = 0.25
    small_strain: float = SMALL_STRAIN
    large_strains: tuple[float, ...] = LARGE_STRAINS
    #: also check the FEM against Hertz (a rigid sphere on a half-space, P2 and P1; the P1 sphere between plates on
    #: the three sphere meshes: about 40 s)
    hertz: bool = True
    #: also solve the small strain with quadratic tets on the same mesh (the P1 reference's own error; minutes on the
    #: fine meshes)
    quadratic: bool = True
    #: also refine every mesh twice (64 times the tets; the fine ones by multigrid) and extrapolate the punches', the
    #: pads' and the bonded cubes' force to the continuum's at the rate their three levels fit (most of an hour for
    #: the three resolutions on two cores)
    converge: bool = True
    #: also solve the large strains (neo-Hookean FEM, the nonlinear MSD: minutes on the fine meshes)
    large: bool = True


def _check_settings(settings: ComparisonSettings) -> None:
    for c in settings.cases:
        if c not in CASES:
            raise ConfigError(f"case = {c!r} is not allowed; choose from {list(CASES)}")
    for r in settings.resolutions:
        _resolution_name(r)
    lame(1.0, settings.poisson)
    for s in (settings.small_strain, *settings.large_strains):
        if not 0.0 < s <= 0.3:
            raise ConfigError(f"strain = {s!r} must be in (0, 0.3]")


def _derivation_models(case: LoadCase, params: TissueParams, poisson: float) -> dict[str, TissueModel]:
    """The linear networks of :data:`DERIVATIONS` on the case's mesh but the calibrated one (fitted later)."""
    mesh, E = case.mesh, params.youngs_modulus_pa
    base = msd_model(mesh, params, stiffness_rule="van_gelder", contact_calibration="none")
    models = {"van_gelder": base, "lloyd": msd_model(mesh, params, stiffness_rule="lloyd", contact_calibration="none"),
              "fem-fit": with_springs(base, fem_fit_springs(mesh, E, poisson))}
    if "-j1" in case.name:  # (the grid rule is made for the alternating grid: grid_springs)
        models["grid"] = with_springs(base, grid_springs(mesh, E, case.lattice))
    return models


def compare(params: TissueParams, settings: ComparisonSettings = ComparisonSettings()) -> dict:
    """MSD against FEM per load case, mesh and strain; the effective Poisson ratio; the FEM's closed-form checks;
    verdicts. The MSD is ``params`` (its Young's modulus is the FEM's) with the spring derivations of
    :data:`DERIVATIONS`; at the large strains the shipped derivation and the calibrated one (its factor fitted at the
    small strain on the same case and mesh) are solved with the full nonlinear spring law and volume barrier, and
    once more with linear springs and no barrier (what the stiffening and the barrier add)."""
    _check_settings(settings)
    E, nu = params.youngs_modulus_pa, settings.poisson
    checks = [bar_check(E, 0.45), confined_check(E, 0.45), neo_hookean_bar_check(E, 0.45)]
    hertz = hertz_p1 = None
    if settings.hertz:
        checks.append(halfspace_hertz_check(E, nu))
        # reported, not checked: P1's own error in contact, on the same grid and on the project's spheres
        hertz_p1 = halfspace_hertz_check(E, nu, HalfSpaceHertz(order=1, cells_per_contact_radius=6.0, grading=1.15,
                                                               extent=15.0))
        hertz = hertz_check(E, nu)
    rows: list[dict] = []
    poisson: dict[str, dict[str, float]] = {}
    converged: dict[str, dict] = {}
    curves: list[dict] = []
    strains = [settings.small_strain, *settings.large_strains]
    for name in settings.cases:
        for res in map(_resolution_name, settings.resolutions):  # (rows name it as the fit and the verdicts look it up)
            case = load_case(name, res)
            models = _derivation_models(case, params, nu)
            base = models["van_gelder"]
            k_fem, u_fem = fem_linear_forces(case, E, nu, [1.0 / case.height_m])
            k_fem = float(k_fem[0])
            # (P2 of a pad's traction is not built: the pads are compared with P1 and its refinements)
            k_p2 = fem_quadratic_force(case, E, nu) if settings.quadratic and not case.padded else None
            limit = None
            if settings.converge and not name.startswith("cube-slip"):  # (uniform strain: P1 is exact)
                # (every mesh split twice: its own rate, fitted on its three levels)
                limit = converged[f"{name}/{res}"] = converged_linear_force(case, E, nu, 2)
            k_msd = {}
            for key, m in models.items():
                k_msd[key], u = msd_linear_force(case, m)
                if case.sides is not None and not case.bonded:
                    label = res + ("/j1" if name.endswith("-j1") else "")
                    poisson.setdefault(label, {"fem": poisson_ratio(case, u_fem)})[key] = poisson_ratio(case, u)
            factor = k_fem / k_msd["van_gelder"]
            models["calibrated"] = with_springs(base, base.k1 * factor)
            k_msd["calibrated"] = k_fem
            travel = settings.small_strain * case.height_m
            for key in (k for k in DERIVATIONS if k in k_msd):
                rows.append({"case": name, "resolution": res, "nodes": case.mesh.n_nodes, "derivation": key,
                             "strain": settings.small_strain, "fem": "linear", "msd": "linear springs",
                             "msd_N": k_msd[key] * travel, "fem_N": k_fem * travel,
                             "rel_error": k_msd[key] / k_fem - 1.0,
                             **({"fem_p2_N": k_p2 * travel, "rel_error_p2": k_msd[key] / k_p2 - 1.0}
                                if k_p2 is not None else {}),
                             **({"fem_limit_N": limit["limit_N_per_m"] * travel,
                                 "rel_error_limit": k_msd[key] / limit["limit_N_per_m"] - 1.0} if limit else {}),
                             **({"factor": factor} if key == "calibrated" else {})})
            if name not in LARGE_STRAIN_CASES or not settings.large:
                continue
            try:
                f_nh = fem_neo_hookean_forces(case, E, nu, strains)
            except RuntimeError:  # (reported as NaN: no converged reference at these strains)
                f_nh = np.full(len(strains), math.nan)
            curve = {"case": name, "resolution": res, "strain": strains, "fem_linear_N": [k_fem * s * case.height_m
                                                                                          for s in strains],
                     "fem_neo_hookean_N": f_nh.tolist()}
            for key in ("van_gelder", "calibrated"):
                full, _ = msd_forces(case, models[key], strains)
                lin_model = with_springs(models[key], models[key].k1)
                lin_model.k2 = np.zeros_like(lin_model.k2)
                lin_model.kvol = np.zeros(0)
                plain, _ = msd_forces(case, lin_model, strains)
                curve[f"msd_{key}_N"] = full.tolist()
                curve[f"msd_{key}_plain_N"] = plain.tolist()
                for s, fm, fp, fn in zip(strains, full, plain, f_nh):
                    rows.append({"case": name, "resolution": res, "nodes": case.mesh.n_nodes, "derivation": key,
                                 "strain": s, "fem": "neo-Hookean", "msd": "nonlinear springs + barrier",
                                 "msd_N": float(fm), "fem_N": float(fn), "rel_error": float(fm / fn - 1.0),
                                 "msd_plain_N": float(fp), "plain_rel_error": float(fp / fn - 1.0)})
            curves.append(curve)
    fits = continuum_fit(rows)
    return {"youngs_modulus_pa": E, "poisson": nu, "checks": checks, "hertz": hertz, "hertz_halfspace_p1": hertz_p1,
            "converged": converged, "rows": rows, "continuum_fit": fits, "poisson_ratio": poisson, "curves": curves,
            "verdicts": comparison_verdicts(checks, rows, poisson) + continuum_fit_verdicts(fits)}


def continuum_fit(rows: Sequence[dict]) -> list[dict]:
    """Van Gelder's springs times one factor per mesh, fitted so that the network is the continuum (the refined,
    extrapolated linear FEM) under one load of :data:`LOAD_PAIRS`, and its error under the other load on the same
    mesh, both ways: whether one stiffness correction per mesh makes the network the continuum, or only fits one
    load. Rows of :func:`compare` at the small strain with ``rel_error_limit``; a mesh without both loads is left
    out."""
    err = {(r["case"], r["resolution"]): r["rel_error_limit"] for r in rows
           if r["fem"] == "linear" and r["derivation"] == "van_gelder" and "rel_error_limit" in r}
    out = []
    for punch, pads in LOAD_PAIRS:
        for res in CUBE_CELLS:
            if (punch, res) in err and (pads, res) in err:
                a, b = 1.0 + err[punch, res], 1.0 + err[pads, res]  # (network / continuum under each load)
                out.append({"mesh": punch, "resolution": res, "punch_rel_error": a - 1.0, "pads_rel_error": b - 1.0,
                            "factor_from_punch": 1.0 / a, "pads_rel_error_fitted": b / a - 1.0,
                            "factor_from_pads": 1.0 / b, "punch_rel_error_fitted": a / b - 1.0})
    return out


def continuum_fit_verdicts(fits: Sequence[dict]) -> list[dict]:
    """Per mesh family of :func:`continuum_fit`: the other load within the small-strain band, both ways, on every
    resolution."""
    from .compression import verdict

    out = []
    for mesh in dict.fromkeys(f["mesh"] for f in fits):
        sel = [f for f in fits if f["mesh"] == mesh]
        worst = max(abs(e) if math.isfinite(e) else math.inf  # (a non-finite limit fails, as in _band_verdict)
                    for f in sel for e in (f["pads_rel_error_fitted"], f["punch_rel_error_fitted"]))
        out.append(verdict(f"MSD (van_gelder x one factor per mesh, fitted to the continuum under one load) within "
                           f"{SMALL_STRAIN_RTOL:.0%} of the continuum under the other ({mesh}: punch, pads)",
                           worst <= SMALL_STRAIN_RTOL,
                           ", ".join(f"{f['resolution']} x{f['factor_from_punch']:.3f}: pads "
                                     f"{f['pads_rel_error_fitted']:+.1%}; x{f['factor_from_pads']:.3f}: punch "
                                     f"{f['punch_rel_error_fitted']:+.1%}" for f in sel)))
    return out


def _band_verdict(claim: str, rows: Sequence[dict], error: str, tol: float, note: str = "") -> dict:
    """One verdict: every row's relative error ``rows[i][error]`` within ``tol`` (a non-finite one fails)."""
    from .compression import verdict

    worst = max(abs(r[error]) if math.isfinite(r[error]) else math.inf for r in rows)
    strain = (lambda r: f" {r['strain']:.0%}") if any(r["fem"] == "neo-Hookean" for r in rows) else (lambda r: "")
    return verdict(claim, worst <= tol, ", ".join(f"{r['case']}/{r['resolution']}{strain(r)} {r[error]:+.1%}"
                                                  for r in rows) + note)


def comparison_verdicts(checks: Sequence[dict], rows: Sequence[dict], poisson: dict) -> list[dict]:
    """The acceptance claims, checked on :func:`compare`'s numbers."""
    from .compression import verdict

    out = [verdict("the FEM solver meets its closed forms (" + "; ".join(c["check"] for c in checks) + ")",
                   all(abs(c["rel_error"]) <= FEM_CHECK_RTOL for c in checks),
                   ", ".join(f"{c['rel_error']:+.1e}" for c in checks) + f" (within {FEM_CHECK_RTOL:.0%})")]
    small = [r for r in rows if r["fem"] == "linear"]
    large = [r for r in rows if r["fem"] == "neo-Hookean" and r["strain"] > SMALL_STRAIN + 1e-12]
    band = f"within {SMALL_STRAIN_RTOL:.0%} of the"

    def pool(key: str, rows: list[dict]) -> list[dict]:
        # the grid rule is made for the J1 cube (every interior node a centre of symmetry): on the spleen's mapped
        # split its rows are reported, not claimed
        return [r for r in rows if key != "grid" or r["case"].startswith("cube")]

    def every(key: str) -> str:
        return " on every J1 cube and mesh" if key == "grid" else " on every case and mesh"

    claims = [(key, pool(key, small), "rel_error", f"{band} linear FEM at small strain{every(key)}",
               SMALL_STRAIN_RTOL) for key in DERIVATIONS]
    claims += [(key, pool(key, [r for r in small if "rel_error_p2" in r]), "rel_error_p2",
                f"{band} quadratic (P2) FEM at small strain{every(key)}", SMALL_STRAIN_RTOL)
               for key in ("van_gelder", "lloyd", "grid")]
    claims += [(key, pool(key, [r for r in small if "rel_error_limit" in r]), "rel_error_limit",
                f"{band} converged linear FEM (refined, extrapolated) at small strain{every(key)}",
                SMALL_STRAIN_RTOL) for key in ("van_gelder", "lloyd", "grid")]
    large_claims = [(key, large, "rel_error", f"within {2 * SMALL_STRAIN_RTOL:.0%} of the neo-Hookean FEM at large "
                     "strain", 2 * SMALL_STRAIN_RTOL) for key in ("van_gelder", "calibrated")]
    out += _claim_verdicts(claims)
    for label, p in poisson.items():  # (the octant grid with van Gelder's springs; the J1 grid with the grid rule)
        res, _, j1 = label.partition("/")
        key = "grid" if j1 else "van_gelder"  # (each grid with the springs made for it)
        out.append(verdict(f"the network's effective Poisson ratio ({res} {'J1 ' if j1 else ''}cube, uniaxial stress, "
                           f"{key}) is the continuum's", abs(p[key] - p["fem"]) <= 0.05,
                           ", ".join(f"{k} {v:.3f}" for k, v in p.items())))
    return out + _claim_verdicts(large_claims)


def _claim_verdicts(claims: Sequence[tuple]) -> list[dict]:
    """A verdict per (derivation, rows, error key, claim, tolerance) with rows of that derivation."""
    out = []
    for key, pool, error, what, tol in claims:
        sel = [r for r in pool if r["derivation"] == key]
        if sel:
            small = key == "calibrated" and all(r["fem"] == "linear" for r in sel)
            note = " (factor fitted on each case and mesh)" if small else ""
            out.append(_band_verdict(f"MSD ({key}) {what}", sel, error, tol, note))
    return out


def plot_comparison(result: dict, path) -> object:
    """Force against strain per load case: the FEM (linear, neo-Hookean) and the MSD (shipped, calibrated)."""
    with needs_extra("viz", "the FEM comparison plot"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..physics.config import save_figure

    curves = result["curves"]
    names = list(dict.fromkeys(c["case"] for c in curves))
    fig, axes = plt.subplots(1, len(names) + 1, figsize=(4.2 * (len(names) + 1), 3.8), squeeze=False)
    styles = {"coarse": "-", "medium": "-.", "fine": "--"}
    for ax, name in zip(axes[0], names):
        for c in (c for c in curves if c["case"] == name):
            s = 100.0 * np.concatenate([[0.0], c["strain"]])
            ls = styles.get(c["resolution"], ":")
            for key, label, color in (("fem_linear_N", "FEM linear", "0.6"),
                                      ("fem_neo_hookean_N", "FEM neo-Hookean", "k"),
                                      ("msd_van_gelder_N", "MSD shipped", "C3"),
                                      ("msd_calibrated_N", "MSD calibrated", "C0")):
                ax.plot(s, np.concatenate([[0.0], c[key]]), ls, color=color, label=f"{label} ({c['resolution']})")
        ax.set_title(f"{name}: force vs strain")
        ax.set_xlabel("strain (%)")
        ax.set_ylabel("indenter force (N)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    # the small-strain errors of every derivation, per case and mesh
    ax = axes[0][-1]
    small = [r for r in result["rows"] if r["fem"] == "linear" and r["derivation"] != "calibrated"]
    labels = list(dict.fromkeys(f"{r['case']}/{r['resolution']}" for r in small))
    keys = list(dict.fromkeys(r["derivation"] for r in small))
    for j, key in enumerate(keys):
        vals = [next((100.0 * r["rel_error"] for r in small if r["derivation"] == key
                      and f"{r['case']}/{r['resolution']}" == lab), np.nan) for lab in labels]
        ax.bar(np.arange(len(labels)) + (j - 0.5 * (len(keys) - 1)) * 0.8 / max(1, len(keys)), vals,
               0.8 / max(1, len(keys)), label=key)
    ax.axhspan(-100 * SMALL_STRAIN_RTOL, 100 * SMALL_STRAIN_RTOL, color="0.9", zorder=0)
    ax.set_xticks(np.arange(len(labels)), labels, rotation=45, ha="right", fontsize=7)
    ax.set_ylabel(f"MSD / linear FEM - 1 at {100 * SMALL_STRAIN:g}% (%)")
    ax.set_title("small strain, per spring derivation")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=6)
    return save_figure(fig, path)


def write_comparison_csv(rows: Sequence[dict], path) -> object:
    """One row per case, mesh, derivation and strain (forces in N, errors as fractions)."""
    from ..physics.config import atomic_write

    cols = ["case", "resolution", "nodes", "derivation", "strain", "fem", "msd", "fem_N", "msd_N", "rel_error",
            "fem_p2_N", "rel_error_p2", "fem_limit_N", "rel_error_limit", "msd_plain_N", "plain_rel_error", "factor"]

    def cell(v) -> str:
        return f"{v:.6g}" if isinstance(v, float) else ("" if v is None else str(v))

    lines = [",".join(cols)] + [",".join(cell(r.get(c)) for c in cols) for r in rows]
    return atomic_write(path, lambda p: p.write_text("\n".join(lines) + "\n"))
