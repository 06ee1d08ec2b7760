"""Tetrahedral meshes for the mass-spring-damper tissue model.

Mesh vertices become mass nodes and unique tetrahedron edges become springs. This module
provides

* :class:`TetMesh`: a validated, immutable tet mesh with cached derived data (edges, volumes,
  outward surface triangles, surface nodes) plus named node sets and landmarks;
* :func:`validate_tets`: the checks every mesh passes through (finite coordinates, index range,
  no degenerate / inverted tets, one connected piece, no unused nodes, manifold faces);
* deterministic built-in meshes: :func:`sphere_mesh` (test sample) and :func:`spleen_mesh`
  (a human-spleen-like organ), at the resolutions of :data:`RESOLUTIONS`;
* file I/O through meshio: :func:`load_mesh`, :func:`save_mesh` (atomic) and :func:`build_mesh`.

Built-in meshes are "mapped box" meshes: a structured box grid, every cube split into 6 Kuhn
tetrahedra whose cube diagonal points away from the box centre in each octant (the reflected
Kuhn / 3-D "union jack" split; it is conforming and no tetrahedron gets two faces on two
different box faces), mapped onto a ball / ellipsoid by a radial map (for the sphere
``f(p) = p * ||p||_inf / ||p||_2``, Jacobian determinant ``(||p||_inf/||p||_2)^3 > 0``; for the
elongated spleen the rays start on a core segment of the long axis), then shaped. Minimum
radius-ratio quality: 0.54 for the sphere and 0.33-0.41 for the spleen at every resolution.

Units are SI (metres, m^3) throughout.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .config import atomic_write

__all__ = [
    "MeshError",
    "TetMesh",
    "RESOLUTIONS",
    "MIN_TARGET_NODES",
    "validate_tets",
    "tet_signed_volumes",
    "tet_quality",
    "sphere_mesh",
    "spleen_mesh",
    "load_mesh",
    "save_mesh",
    "build_mesh",
]

#: Target node counts of the named resolutions (the reference paper's spleen had 236 nodes).
RESOLUTIONS: dict[str, int] = {"coarse": 240, "medium": 1000, "fine": 4000, "xfine": 16000}
#: Smallest accepted integer resolution (target node count).
MIN_TARGET_NODES = 20

#: Relative volume below which a tet is degenerate: |V| < DEGENERATE_VOLUME_REL * bbox_diag^3.
DEGENERATE_VOLUME_REL = 1e-12
#: Radius-ratio quality below which a tet is degenerate (a sliver or needle).
DEGENERATE_QUALITY = 1e-3

# Faces of a tet (v0, v1, v2, v3) with positive orientation, ordered so that the right-hand
# normal points out of the tet (face k is opposite vertex k).
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


class MeshError(ValueError):
    """An invalid mesh or mesh request; the message says what is wrong and where."""


# --------------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------------


def tet_signed_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (T,) in m^3; positive for positively oriented tets."""
    p0 = nodes[tets[:, 0]]
    a, b, c = nodes[tets[:, 1]] - p0, nodes[tets[:, 2]] - p0, nodes[tets[:, 3]] - p0
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def tet_quality(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Normalised radius ratio ``3 r_in / r_circ`` (T,): 1 for a regular tet, 0 if flat."""
    p0 = nodes[tets[:, 0]]
    a, b, c = nodes[tets[:, 1]] - p0, nodes[tets[:, 2]] - p0, nodes[tets[:, 3]] - p0
    bxc, cxa, axb = np.cross(b, c), np.cross(c, a), np.cross(a, b)
    vol = np.abs(np.einsum("ij,ij->i", a, bxc)) / 6.0
    # circumcentre (relative to p0) = num / (12 V): r_circ = |num| / (12 V)
    num = np.linalg.norm(
        (a * a).sum(1)[:, None] * bxc + (b * b).sum(1)[:, None] * cxa + (c * c).sum(1)[:, None] * axb,
        axis=1,
    )
    # total face area; r_in = 3 V / area
    area = 0.5 * (
        np.linalg.norm(bxc, axis=1)
        + np.linalg.norm(cxa, axis=1)
        + np.linalg.norm(axb, axis=1)
        + np.linalg.norm(np.cross(b - a, c - a), axis=1)
    )
    denom = area * num
    out = np.zeros(len(tets))
    np.divide(108.0 * vol * vol, denom, out=out, where=denom > 0)
    return np.clip(out, 0.0, 1.0)


def _area_vectors(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Per triangle (S,3): cross product = 2 * area * right-hand unit normal."""
    return np.cross(p[tris[:, 1]] - p[tris[:, 0]], p[tris[:, 2]] - p[tris[:, 0]])


def _vertex_normals(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N,3) of a triangle set; zero rows off the surface."""
    cross = _area_vectors(p, tris)
    idx = tris.ravel()
    acc = np.stack(
        [np.bincount(idx, weights=np.repeat(cross[:, k], 3), minlength=len(p)) for k in range(3)],
        axis=1,
    )
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.zeros_like(acc)
    np.divide(acc, norm, out=out, where=norm > 0)
    return out


def _sort_parity(faces: np.ndarray) -> np.ndarray:
    """Parity (0 even, 1 odd) of the permutation that sorts each row of a (F,3) array."""
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    return ((a > b).astype(np.int64) + (a > c) + (b > c)) % 2


def _boundary_faces(tets: np.ndarray, source: str) -> np.ndarray:
    """Outward-oriented faces that belong to exactly one tet (S,3).

    Raises MeshError for faces shared by more than two tets (non-manifold) or by two tets on
    the same side of the face (overlapping tets).
    """
    faces = tets[:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    ks = key[order]
    new = np.ones(len(ks), dtype=bool)
    new[1:] = np.any(ks[1:] != ks[:-1], axis=1)
    group = np.cumsum(new) - 1
    counts = np.bincount(group)
    if counts.max() > 2:
        g = int(np.argmax(counts > 2))
        f = order[group == g]
        raise MeshError(
            f"{source}: face {key[f[0]].tolist()} is shared by "
            f"{counts[g]} tetrahedra (tets {(f // 4).tolist()}); a tet mesh must be manifold"
        )
    # interior faces: the two oriented copies must have opposite orientation
    par = _sort_parity(faces[order])
    paired = counts[group] == 2
    first = paired & new
    idx = np.flatnonzero(first)
    same = par[idx] == par[idx + 1]
    if np.any(same):
        i = idx[np.argmax(same)]
        t1, t2 = int(order[i] // 4), int(order[i + 1] // 4)
        raise MeshError(
            f"{source}: tetrahedra {t1} and {t2} overlap (they share face "
            f"{key[order[i]].tolist()} from the same side)"
        )
    return faces[order[counts[group] == 1]]


def _components(n_nodes: int, tets: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of the node graph (connectivity through shared nodes)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows = np.repeat(tets[:, 0], 3)
    cols = tets[:, 1:].ravel()
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_nodes, n_nodes))
    n, labels = connected_components(graph, directed=False)
    return int(n), labels


def _as_nodes(nodes, source: str) -> np.ndarray:
    """Nodes as a (N,3) float64 array of finite values, else MeshError."""
    try:
        arr = np.asarray(nodes, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{source}: nodes must be a (N,3) array of floats ({exc})") from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MeshError(f"{source}: nodes must have shape (N,3), got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise MeshError(
            f"{source}: node {i} has a non-finite (NaN/inf) coordinate {arr[i].tolist()} "
            f"({int(bad.sum())} such nodes)"
        )
    return arr


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def validate_tets(nodes, tets, source: str = "mesh") -> np.ndarray:
    """Validate a tet mesh and return its (possibly flipped) tets as (T,4) int64.

    Raises :class:`MeshError` (naming ``source`` and the offending index) for: nodes not (N,3)
    finite floats, tets not (T,4) integers, no tets, indices out of range, a node repeated in a
    tet, degenerate tets, mixed orientation, non-manifold/overlapping faces, unused nodes and
    more than one connected piece. If *all* tets are negatively oriented (a file convention)
    they are all flipped silently.
    """
    pts = _as_nodes(nodes, source)
    t = np.asarray(tets)
    if t.ndim != 2 or t.shape[1] != 4:
        raise MeshError(f"{source}: tets must have shape (T,4), got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise MeshError(f"{source}: tets must be an integer array, got dtype {t.dtype}")
    t = t.astype(np.int64)
    n_nodes, n_tets = len(pts), len(t)
    if n_tets == 0:
        raise MeshError(f"{source}: no tetrahedra (a volume mesh needs at least one tet)")

    out = (t < 0) | (t >= n_nodes)
    if np.any(out):
        i, k = np.argwhere(out)[0]
        raise MeshError(
            f"{source}: tet {i} references node {t[i, k]} which is out of range "
            f"(valid 0..{n_nodes - 1}; {int(out.any(axis=1).sum())} bad tets)"
        )

    st = np.sort(t, axis=1)
    rep = np.any(st[:, 1:] == st[:, :-1], axis=1)
    if np.any(rep):
        i = int(np.argmax(rep))
        raise MeshError(f"{source}: tet {i} repeats a node {t[i].tolist()}")

    vol = tet_signed_volumes(pts, t)
    qual = tet_quality(pts, t)
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    degenerate = (np.abs(vol) < DEGENERATE_VOLUME_REL * diag**3) | (qual < DEGENERATE_QUALITY)
    if np.any(degenerate):
        i = int(np.argmax(degenerate))
        raise MeshError(
            f"{source}: degenerate tet {i} (nodes {t[i].tolist()}, signed volume {vol[i]:.3e} m^3, "
            f"quality {qual[i]:.2e} < {DEGENERATE_QUALITY:g}; {int(degenerate.sum())} degenerate tets)"
        )

    neg = vol < 0
    if np.all(neg):
        t = t[:, [0, 2, 1, 3]]
    elif np.any(neg):
        i = int(np.argmax(neg))
        raise MeshError(
            f"{source}: tet {i} is inverted (signed volume {vol[i]:.3e} m^3) while "
            f"{int((~neg).sum())} of {n_tets} tets are positively oriented (mixed orientation, "
            f"{int(neg.sum())} inverted)"
        )

    used = np.zeros(n_nodes, dtype=bool)
    used[t.ravel()] = True
    if not used.all():
        i = int(np.argmin(used))
        raise MeshError(
            f"{source}: node {i} is not used by any tetrahedron ({int((~used).sum())} unused nodes)"
        )

    n_comp, labels = _components(n_nodes, t)
    if n_comp > 1:
        tet_label = labels[t[:, 0]]
        tets_per = np.bincount(tet_label, minlength=n_comp)
        nodes_per = np.bincount(labels, minlength=n_comp)
        first = [int(np.argmax(tet_label == k)) for k in range(min(n_comp, 5))]
        raise MeshError(
            f"{source}: mesh is not connected: {n_comp} pieces (tets per piece "
            f"{tets_per[:10].tolist()}, nodes per piece {nodes_per[:10].tolist()}; first tet of "
            f"each piece {first}); it must be one connected body"
        )

    _boundary_faces(t, source)  # manifold / overlap checks
    return t


# --------------------------------------------------------------------------------------------
# TetMesh
# --------------------------------------------------------------------------------------------


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated tetrahedral mesh (SI units); arrays are read-only.

    ``nodes`` (N,3) float64 metres; ``tets`` (T,4) int64, positively oriented;
    ``node_sets`` name -> sorted unique int64 node ids; ``landmarks`` name -> (3,) float64 point
    or unit vector. Derived arrays (``edges``, ``tet_volumes``, ``volume``, ``surface_tris``,
    ``surface_nodes``) are computed once in ``__post_init__``.
    """

    nodes: np.ndarray
    tets: np.ndarray
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "mesh"
    # derived (cached) data
    edges: np.ndarray = field(init=False, repr=False)
    tet_volumes: np.ndarray = field(init=False, repr=False)
    volume: float = field(init=False, repr=False)
    surface_tris: np.ndarray = field(init=False, repr=False)
    surface_nodes: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        src = str(self.name)
        nodes = _as_nodes(self.nodes, src).copy()
        tets = validate_tets(nodes, self.tets, src).copy()
        n = len(nodes)
        sets: dict[str, np.ndarray] = {}
        for key, ids in dict(self.node_sets).items():
            arr = np.asarray(ids)
            if arr.dtype == bool:
                if arr.shape != (n,):
                    raise MeshError(f"{src}: boolean node set {key!r} must have shape ({n},)")
                arr = np.flatnonzero(arr)
            if arr.size and not np.issubdtype(arr.dtype, np.integer):
                raise MeshError(f"{src}: node set {key!r} must hold integer node ids")
            arr = np.unique(arr.astype(np.int64).ravel())
            if arr.size and (arr[0] < 0 or arr[-1] >= n):
                bad = arr[0] if arr[0] < 0 else arr[-1]
                raise MeshError(f"{src}: node set {key!r} holds node {bad} out of range 0..{n - 1}")
            sets[str(key)] = _readonly(arr)
        marks: dict[str, np.ndarray] = {}
        for key, val in dict(self.landmarks).items():
            v = np.asarray(val, dtype=np.float64).ravel()
            if v.shape != (3,) or not np.isfinite(v).all():
                raise MeshError(f"{src}: landmark {key!r} must be 3 finite floats, got {v.tolist()}")
            marks[str(key)] = _readonly(v)

        pairs = np.sort(tets[:, _EDGES].reshape(-1, 2), axis=1)
        ekey = np.unique(pairs[:, 0] * np.int64(n) + pairs[:, 1])
        edges = np.stack([ekey // n, ekey % n], axis=1)
        vols = tet_signed_volumes(nodes, tets)
        tris = _boundary_faces(tets, src)
        tris = tris[np.lexsort((tris[:, 2], tris[:, 1], tris[:, 0]))]

        setattr_ = object.__setattr__
        setattr_(self, "nodes", _readonly(nodes))
        setattr_(self, "tets", _readonly(tets))
        setattr_(self, "node_sets", sets)
        setattr_(self, "landmarks", marks)
        setattr_(self, "name", src)
        setattr_(self, "edges", _readonly(edges))
        setattr_(self, "tet_volumes", _readonly(vols))
        setattr_(self, "volume", float(vols.sum()))
        setattr_(self, "surface_tris", _readonly(tris))
        setattr_(self, "surface_nodes", _readonly(np.unique(tris)))

    def __setstate__(self, state: dict) -> None:
        """Unpickle (e.g. into subprocess environments) keeping the arrays read-only."""
        for key, val in state.items():
            if isinstance(val, np.ndarray):
                val = _readonly(val)
            elif isinstance(val, dict):
                val = {k: _readonly(v) if isinstance(v, np.ndarray) else v for k, v in val.items()}
            object.__setattr__(self, key, val)

    def __repr__(self) -> str:
        return (
            f"TetMesh(name={self.name!r}, n_nodes={self.n_nodes}, n_tets={self.n_tets}, "
            f"n_edges={len(self.edges)}, volume={self.volume:.4e} m^3, "
            f"node_sets={sorted(self.node_sets)}, landmarks={sorted(self.landmarks)})"
        )

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return int(self.nodes.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra."""
        return int(self.tets.shape[0])

    def _positions(self, nodes: np.ndarray | None) -> np.ndarray:
        if nodes is None:
            return self.nodes
        p = np.asarray(nodes, dtype=np.float64)
        if p.shape != self.nodes.shape:
            raise MeshError(f"{self.name}: node positions must have shape {self.nodes.shape}, got {p.shape}")
        return p

    def vertex_normals(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """Area-weighted outward unit normals (N,3); zero rows for interior nodes.

        ``nodes`` are deformed positions (default: the rest positions).
        """
        return _vertex_normals(self._positions(nodes), self.surface_tris)

    def surface_vertex_areas(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """Per-node surface area (N,) of the polygon through the midpoints of its surface edges.

        Equals the sum of area/4 over the adjacent surface triangles (so the total is 3/4 of the
        surface area); zero for interior nodes.
        """
        p = self._positions(nodes)
        area = 0.5 * np.linalg.norm(_area_vectors(p, self.surface_tris), axis=1)
        tris = self.surface_tris.ravel()
        return np.bincount(tris, weights=np.repeat(area / 4.0, 3), minlength=self.n_nodes)

    def surface_area(self, nodes: np.ndarray | None = None) -> float:
        """Total boundary area in m^2."""
        cross = _area_vectors(self._positions(nodes), self.surface_tris)
        return float(0.5 * np.linalg.norm(cross, axis=1).sum())

    def quality(self) -> np.ndarray:
        """Normalised radius ratio ``3 r_in / r_circ`` per tet (T,), in (0, 1]."""
        return tet_quality(self.nodes, self.tets)

    def summary(self) -> dict:
        """Plain-Python summary: counts, volume, bounding-box extent, quality, node set sizes."""
        q = self.quality()
        return {
            "name": self.name,
            "n_nodes": self.n_nodes,
            "n_tets": self.n_tets,
            "n_edges": int(len(self.edges)),
            "n_surface_nodes": int(len(self.surface_nodes)),
            "volume_m3": self.volume,
            "bbox_m": [float(v) for v in np.ptp(self.nodes, axis=0)],
            "min_quality": float(q.min()),
            "mean_quality": float(q.mean()),
            "node_sets": {k: int(len(v)) for k, v in self.node_sets.items()},
        }


# --------------------------------------------------------------------------------------------
# Built-in meshes
# --------------------------------------------------------------------------------------------


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


def _kuhn_box(shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Box grid on [-1,1]^3 split into reflected-Kuhn tets: (nodes (N,3), tets (T,4) positive)."""
    nx, ny, nz = shape
    axes = [np.linspace(-1.0, 1.0, k + 1) for k in shape]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1, nz + 1)
    cells = np.stack(np.meshgrid(*(np.arange(k) for k in shape), indexing="ij"), -1).reshape(-1, 3)
    n = np.asarray(shape)
    # per axis, the cube diagonal runs away from the box centre (cells straddling it: +)
    d = np.where(2 * cells + 1 >= n, 1, -1)
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
    box, tets = _kuhn_box(_grid_shape(target, (1.0, 1.0, 1.0)))
    r = 0.5 * diameter_m
    nodes = _box_to_ellipsoid(box, np.array([r, r, r]), np.zeros(3)) + ctr
    surface = np.unique(_boundary_faces(tets, "sphere"))
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
            f"pole_length_m > 0, 0 <= bluntness <= 1; got bluntness={bluntness!r}, bend={bend!r}, core={core!r}, hilum_width={hilum_width!r}, "
            f"hilum_height={hilum_height!r}, pole_length_m={pole_length_m!r}"
        )
    target = _target_nodes(resolution)
    a, b, c = 0.5 * length_m, 0.5 * width_m, 0.5 * thickness_m
    semi = np.array([a, b, c])
    depth, wx, wz = hilum_depth * b, hilum_width * a, hilum_height * c

    box, tets = _kuhn_box(_grid_shape(target, (length_m, width_m, thickness_m)))
    ell = _box_to_ellipsoid(box, semi, np.array([core * a, 0.0, 0.0]))
    # blunt poles: widen the cross-sections by sqrt(1 + k (x/a)^2) (det = 1 + k (x/a)^2 > 0, no inversion);
    # k = 1 turns the ellipsoid's x-profile 1 - (x/a)^2 into 1 - (x/a)^4, a less tapered pole (real
    # spleens have blunt poles, and a grasp on a cone with taper angle alpha needs mu > tan(alpha))
    widen = np.sqrt(1.0 + bluntness * (ell[:, 0] / a) ** 2)
    ell = ell * np.stack([np.ones_like(widen), widen, widen], axis=1)
    bent = _spleen_map(ell, a, b, bend, depth, wx, wz)
    s = (volume_m3 / tet_signed_volumes(bent, tets).sum()) ** (1.0 / 3.0)
    nodes = bent * s
    tris = _boundary_faces(tets, "spleen")

    # landmarks from the bent centreline (ellipsoid x-axis)
    pole_ell = pole_length_m / s
    centre = _spleen_map(np.array([[a, 0.0, 0.0], [a - pole_ell, 0.0, 0.0]]), a, b, bend, depth, wx, wz) * s
    axis = centre[0] - centre[1]
    axis /= np.linalg.norm(axis)
    tip = _point_on_pl_surface(box, nodes, tris, np.array([1.0, 0.0, 0.0]))
    pole = np.flatnonzero((tip - nodes) @ axis <= pole_length_m)

    surf = np.unique(tris)
    normals = _vertex_normals(nodes, tris)
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


# --------------------------------------------------------------------------------------------
# File I/O
# --------------------------------------------------------------------------------------------

_SET_PREFIX = "nodeset:"


def load_mesh(path: str | os.PathLike) -> TetMesh:
    """Load a tet mesh with meshio (.msh, .vtu, .vtk, ... anything meshio reads).

    Only linear ``"tetra"`` cells are used (triangles, lines and vertices are ignored). Node
    sets are restored from meshio point_sets and from point_data masks named
    ``"nodeset:<name>"`` (as written by :func:`save_mesh`); landmarks are not stored in files.
    Unused nodes are an error, not dropped. Every problem raises :class:`MeshError` naming the
    path. The mesh is named after the file stem.
    """
    import meshio

    p = Path(path)
    if not p.exists():
        raise MeshError(f"mesh file not found: {p}")
    if not p.is_file():
        raise MeshError(f"mesh path is not a file: {p}")
    try:
        m = meshio.read(p)
    except meshio.ReadError as exc:
        raise MeshError(f"cannot read mesh file {p} (unknown or unsupported format?): {exc}") from exc
    except Exception as exc:  # meshio raises assorted errors on malformed files
        raise MeshError(f"cannot read mesh file {p}: {type(exc).__name__}: {exc}") from exc

    blocks = [blk.data for blk in m.cells if blk.type == "tetra"]
    if not blocks:
        found = ", ".join(f"{blk.type} x {len(blk.data)}" for blk in m.cells) or "no cells"
        raise MeshError(
            f"{p}: no 'tetra' cells (found: {found}); a linear tetrahedral volume mesh is required"
        )
    tets = np.concatenate(blocks).astype(np.int64)
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim == 2 and pts.shape[1] == 2:
        raise MeshError(f"{p}: points are 2-D; a 3-D tetrahedral mesh is required")

    sets: dict[str, np.ndarray] = {}
    for key, ids in (getattr(m, "point_sets", None) or {}).items():
        sets[str(key)] = np.asarray(ids, dtype=np.int64).ravel()
    for key, data in m.point_data.items():
        if key.startswith(_SET_PREFIX):
            sets[key[len(_SET_PREFIX):]] = np.flatnonzero(np.asarray(data).ravel() > 0.5)
    try:
        return TetMesh(pts, tets, node_sets=sets, name=p.stem)
    except MeshError as exc:
        raise MeshError(f"{p}: {exc}") from exc


def save_mesh(mesh: TetMesh, path: str | os.PathLike, file_format: str | None = None) -> None:
    """Write ``mesh`` with meshio, atomically (temp file in the same directory, then os.replace).

    The format follows the suffix unless ``file_format`` is given; ``.msh`` defaults to
    ``"gmsh22"``. Node sets are stored as point_data masks ``"nodeset:<name>"``; landmarks are
    not stored (meshio drops VTU field data).
    """
    import meshio

    p = Path(path)
    fmt = file_format
    if fmt is None and p.suffix.lower() == ".msh":
        fmt = "gmsh22"
    if not p.parent.is_dir():
        raise MeshError(f"cannot write {p}: directory {p.parent} does not exist")
    point_data = {}
    for key, ids in mesh.node_sets.items():
        mask = np.zeros(mesh.n_nodes, dtype=np.float64)
        mask[ids] = 1.0
        point_data[_SET_PREFIX + key] = mask
    cell_data = {}
    if (fmt or "").startswith("gmsh"):  # explicit zero tags: meshio warns when they are missing
        zeros = np.zeros(mesh.n_tets, dtype=np.int32)
        cell_data = {"gmsh:physical": [zeros], "gmsh:geometrical": [zeros]}
    m = meshio.Mesh(
        points=np.asarray(mesh.nodes),
        cells=[("tetra", np.asarray(mesh.tets))],
        point_data=point_data,
        cell_data=cell_data,
    )
    def write(tmp: Path) -> None:
        try:
            meshio.write(tmp, m, file_format=fmt)
        except Exception as exc:
            raise MeshError(f"cannot write mesh file {p} (format {fmt or p.suffix!r}): {exc}") from exc

    atomic_write(p, write)


def build_mesh(spec: str | os.PathLike, resolution: str | int = "coarse", **kwargs) -> TetMesh:
    """Build a mesh from a spec: ``"sphere"``, ``"spleen"`` or a mesh file path.

    ``resolution`` and ``kwargs`` go to the built-in generator; for a file path the resolution
    is ignored and keyword options are an error.
    """
    key = str(spec).strip().lower() if isinstance(spec, str) else None
    if key == "sphere":
        return sphere_mesh(resolution=resolution, **kwargs)
    if key == "spleen":
        return spleen_mesh(resolution=resolution, **kwargs)
    if kwargs:
        raise MeshError(
            f"options {sorted(kwargs)} only apply to the built-in meshes 'sphere' and 'spleen', "
            f"not to the mesh file {spec!s}"
        )
    return load_mesh(spec)
