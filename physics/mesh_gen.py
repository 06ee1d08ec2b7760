"""The built-in meshes: deterministic "mapped box" tet meshes of the test sphere (:func:`sphere_mesh`) and
of a human-spleen-like organ (:func:`spleen_mesh`) at the resolutions of
:data:`~msdgrasp.physics.mesh.RESOLUTIONS` (the construction is described in :mod:`msdgrasp.physics.mesh`).
"""

from __future__ import annotations

import inspect
import itertools

import numpy as np

from .mesh import MIN_TARGET_NODES, RESOLUTIONS, MeshError, TetMesh, boundary_faces, tet_signed_volumes, vertex_normals

__all__ = ["sphere_mesh", "spleen_mesh"]




def _target_nodes(resolution: str | int) -> int:
    """Target node count for a resolution name or an int >= MIN_TARGET_NODES."""
    if isinstance(resolution, str):
        key = resolution.strip().lower()
        if key in RESOLUTIONS:
            return RESOLUTIONS[key]
        raise MeshError(
            f"unknown resolution={resolution!r}; allowed: {sorted(RESOLUTIONS, key=RESOLUTIONS.get)} "
            f"or an int target node count >= {MIN_TARGET_NODES}"
        )
    if isinstance(resolution, (int, np.integer)) and not isinstance(resolution, bool):
        if resolution >= MIN_TARGET_NODES:
            return int(resolution)
        raise MeshError(
            f"resolution={resolution} is too small: need a target node count >= {MIN_TARGET_NODES}"
        )
    raise MeshError(
        f"resolution must be one of {sorted(RESOLUTIONS, key=RESOLUTIONS.get)} or an int, got {resolution!r}"
    )


def _grid_shape(target: int, extents) -> tuple[int, int, int]:
    """Cell counts (nx, ny, nz) giving ~target nodes with near-cubic cells for the extents."""
    ext = np.asarray(extents, dtype=np.float64)
    h = (np.prod(ext) / target) ** (1.0 / 3.0)
    ideal = ext / h
    ranges = [range(max(2, int(0.6 * v)), max(2, int(np.ceil(1.6 * v))) + 2) for v in ideal]
    best, best_cost = (2, 2, 2), np.inf
    for shape in itertools.product(*ranges):
        n = np.asarray(shape)
        count = float(np.prod(n + 1))
        size_err = abs(np.log(count / target))
        lh = np.log(ext / n)
        cost = size_err + (lh.max() - lh.min()) + (10.0 if size_err > np.log(1.15) else 0.0)
        if cost < best_cost - 1e-12:
            best, best_cost = tuple(int(v) for v in shape), cost
    return best


#: how :func:`kuhn_box` orients each cell's six Kuhn tets
GRID_PATTERNS = ("octant", "alternating", "alternating-shell")


def kuhn_box(shape: tuple[int, int, int], pattern: str = "octant") -> tuple[np.ndarray, np.ndarray]:
    """Box grid on [-1,1]^3 split into reflected-Kuhn tets: (nodes (N,3), tets (T,4) positive).

    ``pattern``: ``"octant"``, each cell's diagonal runs away from the box centre (one Kuhn lattice per octant,
    mirrored at the centre planes: the built-in meshes' grid); ``"alternating"``, each cell is mirrored by the
    parity of its index along each axis (Todd's J1 triangulation), so that every interior node is a centre of
    symmetry; ``"alternating-shell"``, alternating, but along each axis the first and last cells point outward (as
    on the octant grid) along that axis, so that a map onto a curved body flattens fewer cells across a diagonal
    (the alternating grid mapped onto the spleen has degenerate tets at the medium and fine resolutions). A spring
    network on the octant grid is anisotropic within each octant (every diagonal leans the same way) and relaxes
    non-affinely where the octants meet; on the alternating grid with an even number of cells per axis (whose
    mirrored cells balance) it is a cubic crystal under any uniform strain, which
    :func:`msdgrasp.experiments.fem.grid_springs` makes isotropic. The direction is a function of a cell's index
    along each axis alone, so neighbouring cells split their shared face alike (a conforming mesh) for every
    pattern."""
    if pattern not in GRID_PATTERNS:
        raise MeshError(f"pattern = {pattern!r} is not allowed; choose one of {list(GRID_PATTERNS)}")
    nx, ny, nz = shape
    axes = [np.linspace(-1.0, 1.0, k + 1) for k in shape]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    cells = np.stack(np.meshgrid(*(np.arange(k) for k in shape), indexing="ij"), -1).reshape(-1, 3)
    n = np.asarray(shape)
    # per axis, the cube diagonal runs away from the box centre (cells straddling it: +), or alternates cell by cell
    outward, alternate = np.where(2 * cells + 1 >= n, 1, -1), np.where(cells % 2 == 0, 1, -1)
    d = {"octant": outward, "alternating": alternate,
         "alternating-shell": np.where((cells == 0) | (cells == n - 1), outward, alternate)}[pattern]
    start = np.where(d > 0, cells, cells + 1)
    tets = []
    for perm in itertools.permutations(range(3)):
        cur = start.copy()
        verts = [idx[cur[:, 0], cur[:, 1], cur[:, 2]]]
        for ax in perm:
            cur[:, ax] += d[:, ax]
            verts.append(idx[cur[:, 0], cur[:, 1], cur[:, 2]])
        tets.append(np.stack(verts, axis=1))
    t = np.concatenate(tets).astype(np.int64)
    neg = tet_signed_volumes(grid, t) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return grid, t


def _box_to_ellipsoid(box: np.ndarray, semi: np.ndarray, core: np.ndarray) -> np.ndarray:
    """Map the box [-1,1]^3 onto the ellipsoid with semi-axes ``semi`` (metres).

    With ``p = box * semi`` and ``C = clip(p, -core, core)`` (nearest point of the core box),
    ``p`` moves along the ray from ``C`` so that the box boundary lands on the ellipsoid:
    ``F(p) = C + (p - C) * t_E / t_B`` (``t_B``, ``t_E``: ray parameters of the box and ellipsoid
    exits). Away from the core every piece is a radial map with a degree-0 homogeneous factor,
    hence Jacobian determinant > 0. ``core = 0`` gives the radial map
    ``p * ||p/semi||_inf / ||p/semi||_2``; a core segment along the long axis of an elongated
    ellipsoid keeps rays near-normal to its flat faces (better tets).
    """
    p = box * semi
    c = np.clip(p, -core, core)
    d = p - c
    inv_tb = np.abs(d / (semi - core)).max(axis=1)  # ||d/h||_inf = 1 / t_B
    ds, cs = d / semi, c / semi
    qa = (ds * ds).sum(axis=1)
    qb = (cs * ds).sum(axis=1)
    qc = (cs * cs).sum(axis=1) - 1.0
    out = p.copy()
    m = qa > 0
    t_e = (-qb[m] + np.sqrt(qb[m] ** 2 - qa[m] * qc[m])) / qa[m]
    out[m] = c[m] + d[m] * (t_e * inv_tb[m])[:, None]
    return out


def _point_on_pl_surface(box: np.ndarray, mapped: np.ndarray, tris: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Image under the piecewise-linear map box->mapped of a point q on the box boundary."""
    axis = int(np.argmax(np.abs(q)))
    side = np.sign(q[axis])
    on = np.all(np.isclose(box[tris][:, :, axis], side), axis=1)
    cand = tris[on]
    other = [k for k in range(3) if k != axis]
    a, b, c = (box[cand[:, k]][:, other] for k in range(3))
    v0, v1, v2 = b - a, c - a, q[other] - a
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    l1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
    l2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
    lam = np.stack([1 - l1 - l2, l1, l2], axis=1)
    k = int(np.argmax(lam.min(axis=1)))
    return lam[k] @ mapped[cand[k]]


def sphere_mesh(
    diameter_m: float = 0.05, resolution: str | int = "coarse", center=(0.0, 0.0, 0.0)
) -> TetMesh:
    """Deterministic tet mesh of a solid sphere (mapped box).

    Node sets: ``"surface"``. Landmarks: ``"center"``. The polyhedral volume is slightly
    smaller than 4/3 pi r^3 (all surface nodes lie on the sphere).
    """
    if not (np.isfinite(diameter_m) and diameter_m > 0):
        raise MeshError(f"sphere diameter_m must be > 0, got {diameter_m!r}")
    ctr = np.asarray(center, dtype=np.float64).ravel()
    if ctr.shape != (3,) or not np.isfinite(ctr).all():
        raise MeshError(f"sphere center must be 3 finite floats, got {center!r}")
    target = _target_nodes(resolution)
    box, tets = kuhn_box(_grid_shape(target, (1.0, 1.0, 1.0)))
    r = 0.5 * diameter_m
    nodes = _box_to_ellipsoid(box, np.array([r, r, r]), np.zeros(3)) + ctr
    surface = np.unique(boundary_faces(tets, "sphere"))
    return TetMesh(nodes, tets, node_sets={"surface": surface}, landmarks={"center": ctr}, name="sphere")


def _spleen_map(
    e: np.ndarray, a: float, b: float, beta: float, depth: float, wx: float, wz: float
) -> np.ndarray:
    """Ellipsoid coordinates -> bent, hilum-indented coordinates (before the volume scaling).

    Crescent shear ``y' = y + beta*b*(x/a)^2`` (det 1), then hilum indentation
    ``y'' = y' - depth*exp(-(x/wx)^2-(z/wz)^2)*g(y)``, ``g = (y+b)/(2b)`` (0 lateral, 1 medial);
    ``dy''/dy = 1 - depth*w/(2b) > 0`` for ``depth < 2b``.
    """
    x, y, z = e[:, 0], e[:, 1], e[:, 2]
    g = np.clip((y + b) / (2.0 * b), 0.0, 1.0)
    w = np.exp(-((x / wx) ** 2) - (z / wz) ** 2)
    y2 = y + beta * b * (x / a) ** 2 - depth * w * g
    return np.stack([x, y2, z], axis=1)


def spleen_mesh(
    resolution: str | int = "coarse",
    length_m: float = 0.11,
    width_m: float = 0.07,
    thickness_m: float = 0.04,
    volume_m3: float = 140e-6,
    *,
    bend: float = 0.4,
    hilum_depth: float = 0.3,
    hilum_width: float = 0.45,
    hilum_height: float = 0.6,
    pole_length_m: float = 0.04,
    core: float = 0.4,
    bluntness: float = 1.0,
) -> TetMesh:
    """Deterministic tet mesh of a human-spleen-like organ ("coffee bean" crescent with a hilum).

    Coordinates (metres): origin at the centre of the unbent ellipsoid; ``x`` craniocaudal long
    axis (+x = inferior pole), ``y`` medial (+y) - lateral (-y), ``z`` thickness
    (anterior-posterior); ``a, b, c = (length, width, thickness)/2``. Construction: a box grid
    with near-cubic cells is mapped onto the ellipsoid with semi-axes ``(a, b, c)``
    (:func:`_box_to_ellipsoid`, rays from a core segment ``|x| <= core*a``); bent into a
    crescent by the volume-preserving shear ``y += bend*b*(x/a)^2`` (tips move medially); a
    hilum is indented on the medial face (Gaussian of half-widths ``hilum_width*a`` in x and
    ``hilum_height*c`` in z, depth ``hilum_depth*b``, so the medial face is concave around the
    hilum); finally everything is scaled uniformly about the origin so the mesh volume equals
    ``volume_m3`` (the bounding box is therefore close to, not exactly,
    length x width x thickness). ``bend`` trades crescent shape for tet quality (min quality
    ~0.33 at 0.4, ~0.26 at 0.6).

    Node sets: ``"surface"``; ``"hilum"`` (medial surface nodes inside the indentation,
    ``(x/wx)^2 + (z/wz)^2 <= 1.5`` in ellipsoid coordinates, whose outward normal has
    y-component > 0.5; ~7% of the surface nodes); ``"inferior_pole"`` (all nodes within ``pole_length_m`` of
    the inferior tip measured along the pole axis). Landmarks: ``"inferior_pole_tip"`` (the
    mesh-surface point at the +x end of the bent centreline), ``"inferior_pole_axis"`` (unit
    chord direction of the bent centreline over the pole segment, pointing out of the organ
    toward the tip) and ``"hilum_center"`` (centroid of the hilum nodes).
    """
    dims = {"length_m": length_m, "width_m": width_m, "thickness_m": thickness_m, "volume_m3": volume_m3}
    for key, val in dims.items():
        if not (np.isfinite(val) and val > 0):
            raise MeshError(f"spleen {key} must be > 0, got {val!r}")
    if not 0.0 <= hilum_depth < 1.0:
        raise MeshError(f"spleen hilum_depth must be in [0, 1) (fraction of width/2), got {hilum_depth!r}")
    if not (0.0 <= bend <= 1.0 and 0.0 <= core < 1.0 and hilum_width > 0 and hilum_height > 0
            and pole_length_m > 0 and 0.0 <= bluntness <= 1.0):
        raise MeshError(
            f"spleen needs 0 <= bend <= 1, 0 <= core < 1, hilum_width > 0, hilum_height > 0, "
            f"pole_length_m > 0, 0 <= bluntness <= 1; got bluntness={bluntness!r}, bend={bend!r}, core={core!r}, "
            f"hilum_width={hilum_width!r}, "
            f"hilum_height={hilum_height!r}, pole_length_m={pole_length_m!r}"
        )
    a, b, c = 0.5 * length_m, 0.5 * width_m, 0.5 * thickness_m
    semi = np.array([a, b, c])
    depth, wx, wz = hilum_depth * b, hilum_width * a, hilum_height * c

    box, tets = kuhn_box(_spleen_grid_shape(resolution, (length_m, width_m, thickness_m)))
    ell = _box_to_ellipsoid(box, semi, np.array([core * a, 0.0, 0.0]))
    # blunt poles: widen the cross-sections by sqrt(1 + k (x/a)^2) (det = 1 + k (x/a)^2 > 0, no inversion);
    # k = 1 turns the ellipsoid's x-profile 1 - (x/a)^2 into 1 - (x/a)^4, a less tapered pole (real
    # spleens have blunt poles, and a grasp on a cone with taper angle alpha needs mu > tan(alpha))
    widen = np.sqrt(1.0 + bluntness * (ell[:, 0] / a) ** 2)
    ell = ell * np.stack([np.ones_like(widen), widen, widen], axis=1)
    bent = _spleen_map(ell, a, b, bend, depth, wx, wz)
    s = (volume_m3 / tet_signed_volumes(bent, tets).sum()) ** (1.0 / 3.0)
    nodes = bent * s
    tris = boundary_faces(tets, "spleen")

    # landmarks from the bent centreline (ellipsoid x-axis)
    pole_ell = pole_length_m / s
    centre = _spleen_map(np.array([[a, 0.0, 0.0], [a - pole_ell, 0.0, 0.0]]), a, b, bend, depth, wx, wz) * s
    axis = centre[0] - centre[1]
    axis /= np.linalg.norm(axis)
    tip = _point_on_pl_surface(box, nodes, tris, np.array([1.0, 0.0, 0.0]))
    pole = np.flatnonzero((tip - nodes) @ axis <= pole_length_m)

    surf = np.unique(tris)
    normals = vertex_normals(nodes, tris)
    w = np.exp(-((ell[:, 0] / wx) ** 2) - (ell[:, 2] / wz) ** 2)
    in_dent = (w >= np.exp(-1.5)) & (ell[:, 1] > 0)
    hilum = surf[in_dent[surf] & (normals[surf, 1] > 0.5)]
    if hilum.size == 0:
        raise MeshError("spleen: no surface node inside the hilum indentation (mesh too coarse?)")

    return TetMesh(
        nodes,
        tets,
        node_sets={"surface": surf, "hilum": hilum, "inferior_pole": pole},
        landmarks={
            "inferior_pole_tip": tip,
            "inferior_pole_axis": axis,
            "hilum_center": nodes[hilum].mean(axis=0),
        },
        name="spleen",
    )


def kuhn_lattice(shape: tuple[int, int, int]) -> np.ndarray:
    """The integer grid coordinates (N, 3) of :func:`kuhn_box`'s nodes, in its node order: an edge of its tets runs
    along a grid axis where they differ in one coordinate, along a diagonal where in two or three."""
    return np.stack(np.unravel_index(np.arange(int(np.prod(np.asarray(shape) + 1))),
                                     tuple(k + 1 for k in shape)), axis=1).astype(np.int64)


def _spleen_grid_shape(resolution: str | int,
                       extents: tuple[float, float, float] | None = None) -> tuple[int, int, int]:
    """The cells per axis of the box grid :func:`spleen_mesh` maps (``extents``: its length, width and thickness, m;
    None: its defaults)."""
    if extents is None:
        extents = tuple(inspect.signature(spleen_mesh).parameters[k].default
                        for k in ("length_m", "width_m", "thickness_m"))
    return _grid_shape(_target_nodes(resolution), extents)


def spleen_lattice(resolution: str | int = "coarse") -> np.ndarray:
    """:func:`kuhn_lattice` of the box grid that the default :func:`spleen_mesh` maps (its nodes keep the grid's
    order)."""
    return kuhn_lattice(_spleen_grid_shape(resolution))


def spleen_on_grid(resolution: str | int = "coarse", pattern: str = "alternating-shell") -> TetMesh:
    """The default built-in spleen's nodes, node sets and landmarks (:func:`spleen_mesh`) with its box grid split by
    ``pattern`` (:func:`kuhn_box`) instead of the octant grid: the same body with other tets (its surface's quads
    split along other diagonals). MeshError where a tet degenerates (the alternating grid at medium and fine)."""
    spleen = spleen_mesh(resolution)
    _, tets = kuhn_box(_spleen_grid_shape(resolution), pattern)
    return TetMesh(spleen.nodes, tets, node_sets=dict(spleen.node_sets), landmarks=dict(spleen.landmarks),
                   name=f"spleen-{pattern}")
