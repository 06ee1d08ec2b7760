"""Tetrahedral meshes for the mass-spring-damper tissue model.

Mesh vertices become mass nodes and unique tetrahedron edges become springs. This module
provides

* :class:`TetMesh`: a validated, immutable tet mesh with cached derived data (edges, volumes,
  outward surface triangles, surface nodes) plus named node sets and landmarks;
* :func:`validate_tets`: the checks every mesh passes through (finite coordinates, index range,
  no degenerate / inverted tets, one connected piece, no unused nodes, manifold faces);
* the named resolutions (:data:`RESOLUTIONS`).

The built-in meshes are in :mod:`~msdgrasp.physics.mesh_gen` (:func:`sphere_mesh`, :func:`spleen_mesh`),
file I/O through meshio in :mod:`~msdgrasp.physics.mesh_io` (:func:`load_mesh`, :func:`save_mesh`,
:func:`build_mesh`). Built-in meshes are "mapped box" meshes: a structured box grid, every cube split into 6 Kuhn
tetrahedra whose cube diagonal points away from the box centre in each octant (the reflected
Kuhn / 3-D "union jack" split; it is conforming and no tetrahedron gets two faces on two
different box faces), mapped onto a ball / ellipsoid by a radial map (for the sphere
``f(p) = p * ||p||_inf / ||p||_2``, Jacobian determinant ``(||p||_inf/||p||_2)^3 > 0``; for the
elongated spleen the rays start on a core segment of the long axis), then shaped. Minimum
radius-ratio quality: 0.54 for the sphere and 0.33-0.41 for the spleen at every resolution.

Units are SI (metres, m^3) throughout.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


__all__ = [
    "MeshError",
    "TetMesh",
    "RESOLUTIONS",
    "MIN_TARGET_NODES",
    "validate_tets",
    "tet_signed_volumes",
    "tet_quality",
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


def vertex_normals(p: np.ndarray, tris: np.ndarray) -> np.ndarray:
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


def boundary_faces(tets: np.ndarray, source: str) -> np.ndarray:
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

    boundary_faces(t, source)  # manifold / overlap checks
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
        tris = boundary_faces(tets, src)
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
        return vertex_normals(self._positions(nodes), self.surface_tris)

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
