"""How the shipped gmsh meshes are made; ``msdgrasp meshes [--check]`` regenerates them (or compares).

The sphere:
The mapped-box generator of :func:`msdgrasp.physics.mesh_gen.sphere_mesh` puts a flat 4-node facet at each
pole of the coarse sphere, so plates meet a flat punch (force ~ travel) instead of a curved surface
(Hertz: force ~ travel^1.5), and node-based contact converges slowly with refinement. gmsh's
Frontal-Delaunay surface mesher samples the sphere evenly (a node at each pole, rings around it) and its
Delaunay volume mesher, followed by Netgen's optimiser, fills it with well-shaped tets.

The spleen (``spleen-even``): the built-in spleen's surface at each resolution, kept triangle for triangle, filled by
gmsh's Delaunay volume mesher and Netgen's optimiser instead of the mapped Kuhn grid, whose spring network is
anisotropic (docs/validation.md): the same organ, the same surface and jaws' footprints, an unstructured interior.

Deterministic for a given gmsh version (single thread, fixed seed): :data:`SIZES` and :data:`GMSH_VERSION`
are the record of how the files were made. ``msdgrasp meshes --check`` regenerates in memory and compares with the
shipped files (same tets, coordinates within 1e-12 m).
"""

from __future__ import annotations

import numpy as np

#: gmsh version the shipped files were made with
GMSH_VERSION = "4.15.2"
#: target edge length (m) per resolution for the 50 mm sphere (radius 25 mm): ~256 / ~1000 / ~4000 nodes
SIZES: dict[str, float] = {"coarse": 0.0075, "medium": 0.0042, "fine": 0.0027}
RADIUS_M = 0.025


def _gmsh():
    try:
        import gmsh
    except ModuleNotFoundError:
        raise ImportError("regenerating the meshes needs gmsh, which is not installed: "
                          "pip install 'msdgrasp[meshing]'") from None
    return gmsh


def _tetrahedralize(name: str, build) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """gmsh's Delaunay tets (then Netgen's optimiser) of the model ``build(gmsh)`` adds: (node tags, node positions
    (N, 3) m, the tets' node tags), single-threaded with a fixed seed."""
    gmsh = _gmsh()
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.model.add(name)
        build(gmsh)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay volume
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.optimize("Netgen")
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, _, enodes = gmsh.model.mesh.getElements(3)
    finally:
        gmsh.finalize()
    return np.asarray(tags, dtype=np.int64), np.asarray(xyz, dtype=np.float64).reshape(-1, 3), \
        np.asarray(enodes[0], dtype=np.int64)


def sphere_points_and_tets(size_m: float, radius_m: float = RADIUS_M) -> tuple[np.ndarray, np.ndarray]:
    """(nodes (N, 3) m, tets (T, 4)) of a gmsh-meshed solid sphere centred at the origin."""
    def build(gmsh) -> None:
        gmsh.model.occ.addSphere(0.0, 0.0, 0.0, radius_m)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", size_m)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size_m)
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay surfaces

    tags, nodes, tet_tags = _tetrahedralize("sphere", build)
    index = {int(t): i for i, t in enumerate(tags)}
    tets = np.array([index[int(t)] for t in tet_tags], dtype=np.int64).reshape(-1, 4)
    used = np.unique(tets)  # drop geometry-only nodes (none expected) and renumber densely
    remap = np.full(len(nodes), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return nodes[used], remap[tets]


#: the built-in spleen's resolutions whose surfaces are filled (``spleen-even``)
SPLEEN_RESOLUTIONS = ("coarse", "medium", "fine")


def fill_surface(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nodes (N, 3) m, tets (T, 4)) filling the closed surface ``points`` (S, 3) m / ``triangles`` (F, 3), kept node
    for node and triangle for triangle, with gmsh's Delaunay tets and Netgen's optimiser; the surface's points are the
    first S nodes, in their order (found by position: gmsh renumbers)."""
    from scipy.spatial import cKDTree

    def build(gmsh) -> None:
        face = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, face, list(range(1, len(points) + 1)), np.asarray(points).ravel().tolist())
        gmsh.model.mesh.addElementsByType(face, 2, [], (np.asarray(triangles) + 1).ravel().tolist())
        gmsh.model.geo.addVolume([gmsh.model.geo.addSurfaceLoop([face])])
        gmsh.model.geo.synchronize()

    tags, nodes, tet_tags = _tetrahedralize("fill", build)
    dist, first = cKDTree(nodes).query(points)
    if dist.max() > 1e-12 or len(np.unique(first)) != len(points):
        raise RuntimeError(f"gmsh moved the surface's points (by up to {dist.max():.1e} m)")
    order = np.concatenate([first, np.setdiff1d(np.arange(len(nodes)), first)])
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags[order]] = np.arange(len(order))
    tets = index[tet_tags].reshape(-1, 4)
    if len(np.unique(tets)) != len(order):
        raise RuntimeError("gmsh left nodes outside every tet")
    return nodes[order], tets


def orient(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets with positive signed volume (swap two vertices of the others)."""
    p0 = nodes[tets[:, 0]]
    vol = np.einsum("ij,ij->i", nodes[tets[:, 1]] - p0, np.cross(nodes[tets[:, 2]] - p0, nodes[tets[:, 3]] - p0))
    out = tets.copy()
    out[vol < 0] = out[vol < 0][:, [0, 2, 1, 3]]
    return out
