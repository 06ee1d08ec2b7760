"""Tests for msdgrasp.physics.mesh: built-in meshes, validation and file I/O."""

from __future__ import annotations

import functools
import os

import numpy as np
import pytest

from msdgrasp.physics.mesh import RESOLUTIONS, MeshError, TetMesh, tet_quality, validate_tets
from msdgrasp.physics.mesh_gen import (GRID_PATTERNS, kuhn_box, kuhn_lattice, sphere_mesh, spleen_lattice, spleen_mesh,
                                       spleen_on_grid)
from msdgrasp.physics.mesh_io import build_mesh, load_mesh, save_mesh

import meshio  # noqa: E402  (a dependency: a missing meshio fails, never skips)

# Minimum radius-ratio quality the generators achieve (sphere 0.541 at every resolution; spleen
# 0.405 coarse / 0.375 medium / 0.33 xfine); thresholds leave a margin but catch slivers.
MIN_QUALITY = {"sphere": 0.5, "spleen": 0.3}


@functools.lru_cache(maxsize=None)
def get_mesh(kind: str, resolution: str) -> TetMesh:
    return sphere_mesh(resolution=resolution) if kind == "sphere" else spleen_mesh(resolution=resolution)


CASES = [(k, r) for k in ("sphere", "spleen") for r in ("coarse", "medium")]


def unit_tet_nodes() -> np.ndarray:
    return np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)


# ------------------------------------------------------------------------------------------
# Generated meshes: size, validity, quality, topology
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["sphere", "spleen"])
@pytest.mark.parametrize("resolution", ["coarse", "medium", "fine"])
def test_node_count_near_target(kind, resolution):
    mesh = get_mesh(kind, resolution)
    target = RESOLUTIONS[resolution]
    assert abs(mesh.n_nodes / target - 1.0) <= 0.15, (mesh.n_nodes, target)


@pytest.mark.parametrize("kind,resolution", CASES)
def test_valid_positive_good_quality(kind, resolution):
    mesh = get_mesh(kind, resolution)
    assert mesh.nodes.dtype == np.float64 and mesh.nodes.shape == (mesh.n_nodes, 3)
    assert mesh.tets.dtype == np.int64 and mesh.tets.shape == (mesh.n_tets, 4)
    assert np.all(mesh.tet_volumes > 0)
    q = mesh.quality()
    assert q.min() > MIN_QUALITY[kind], q.min()
    assert q.max() <= 1.0 + 1e-12
    # re-validation is a no-op for a good mesh (no flips)
    np.testing.assert_array_equal(validate_tets(mesh.nodes, mesh.tets), mesh.tets)


@pytest.mark.parametrize("kind,resolution", CASES)
def test_one_piece_and_ball_topology(kind, resolution):
    mesh = get_mesh(kind, resolution)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = mesh.edges
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(mesh.n_nodes,) * 2)
    n_comp, _ = connected_components(g, directed=False)
    assert n_comp == 1
    # solid ball: V - E + F - T == 1 (F counts all unique faces, interior ones twice-shared)
    n_faces = (4 * mesh.n_tets + len(mesh.surface_tris)) // 2
    assert mesh.n_nodes - len(mesh.edges) + n_faces - mesh.n_tets == 1


@pytest.mark.parametrize("kind,resolution", CASES)
def test_edges_unique_sorted(kind, resolution):
    mesh = get_mesh(kind, resolution)
    e = mesh.edges
    assert np.all(e[:, 0] < e[:, 1])
    key = e[:, 0] * mesh.n_nodes + e[:, 1]
    assert np.all(np.diff(key) > 0)  # unique and lexicographically sorted
    # every tet edge is present, nothing else
    t = mesh.tets
    te = np.sort(np.stack([t[:, [0, 0, 0, 1, 1, 2]].ravel(), t[:, [1, 2, 3, 2, 3, 3]].ravel()], 1), 1)
    np.testing.assert_array_equal(np.unique(te[:, 0] * mesh.n_nodes + te[:, 1]), key)


@pytest.mark.parametrize("kind,resolution", CASES)
def test_surface_closed_oriented_sphere_like(kind, resolution):
    mesh = get_mesh(kind, resolution)
    tris = mesh.surface_tris
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    n = mesh.n_nodes
    dkey = directed[:, 0] * n + directed[:, 1]
    # consistently oriented closed surface: every directed edge exactly once, its reverse too
    assert len(np.unique(dkey)) == len(dkey)
    assert np.all(np.isin(directed[:, 1] * n + directed[:, 0], dkey))
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    assert np.all(counts == 2)
    v, ecount, f = len(mesh.surface_nodes), len(counts), len(tris)
    assert v - ecount + f == 2
    np.testing.assert_array_equal(mesh.surface_nodes, np.unique(tris))
    assert set(mesh.node_sets["surface"].tolist()) == set(mesh.surface_nodes.tolist())


@pytest.mark.parametrize("kind,resolution", CASES)
def test_outward_normals_divergence_theorem(kind, resolution):
    mesh = get_mesh(kind, resolution)
    p, t = mesh.nodes, mesh.surface_tris
    area_vec = 0.5 * np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    centroid = p[t].mean(axis=1)
    vol = np.einsum("ij,ij->", centroid, area_vec) / 3.0
    # exact identity for a closed outward-oriented polyhedron (up to round-off)
    assert abs(vol - mesh.volume) <= 1e-9 * mesh.volume


@pytest.mark.parametrize("kind,resolution", CASES)
def test_surface_vertex_areas_sum(kind, resolution):
    mesh = get_mesh(kind, resolution)
    areas = mesh.surface_vertex_areas()
    assert areas.shape == (mesh.n_nodes,)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), mesh.surface_nodes)
    assert np.all(areas[interior] == 0) and np.all(areas[mesh.surface_nodes] > 0)
    np.testing.assert_allclose(areas.sum(), 0.75 * mesh.surface_area(), rtol=1e-12)


def test_sphere_volume_and_normals():
    r = 0.025
    exact = 4.0 / 3.0 * np.pi * r**3
    med = get_mesh("sphere", "medium")
    # inscribed polyhedron: smaller than the ball, within 3% at medium (6% at coarse)
    assert 0.97 * exact < med.volume < exact
    assert 0.94 * exact < get_mesh("sphere", "coarse").volume < exact
    s = med.surface_nodes
    np.testing.assert_allclose(np.linalg.norm(med.nodes[s], axis=1), r, rtol=1e-12)
    n = med.vertex_normals()
    radial = med.nodes[s] / r
    assert np.min(np.einsum("ij,ij->i", n[s], radial)) > 0.95  # outward, ~radial
    interior = np.setdiff1d(np.arange(med.n_nodes), s)
    assert np.all(n[interior] == 0)
    np.testing.assert_allclose(np.linalg.norm(n[s], axis=1), 1.0, rtol=1e-12)
    np.testing.assert_array_equal(med.landmarks["center"], np.zeros(3))


def test_sphere_diameter_center_and_deformed_normals():
    c = np.array([0.1, -0.2, 0.3])
    m = sphere_mesh(diameter_m=0.02, resolution="coarse", center=c)
    np.testing.assert_allclose(np.linalg.norm(m.nodes[m.surface_nodes] - c, axis=1), 0.01, rtol=1e-12)
    np.testing.assert_allclose(m.landmarks["center"], c)
    # normals are invariant under translation + uniform scaling of the positions
    moved = 3.0 * m.nodes + np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(m.vertex_normals(moved), m.vertex_normals(), atol=1e-12)
    np.testing.assert_allclose(m.surface_vertex_areas(moved), 9.0 * m.surface_vertex_areas(), rtol=1e-12)
    with pytest.raises(MeshError, match="shape"):
        m.vertex_normals(m.nodes[:-1])


# ------------------------------------------------------------------------------------------
# Spleen geometry, node sets and landmarks
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("resolution", ["coarse", "medium"])
def test_spleen_volume_and_bbox(resolution):
    mesh = get_mesh("spleen", resolution)
    assert abs(mesh.volume / 140e-6 - 1.0) < 0.01
    ext = np.ptp(mesh.nodes, axis=0) * 100.0  # cm
    assert 9.0 < ext[0] < 13.0 and 5.5 < ext[1] < 8.5 and 3.0 < ext[2] < 5.0, ext


@pytest.mark.parametrize("resolution", ["coarse", "medium"])
def test_spleen_node_sets_and_landmarks(resolution):
    mesh = get_mesh("spleen", resolution)
    surf = mesh.surface_nodes
    normals = mesh.vertex_normals()
    hilum = mesh.node_sets["hilum"]
    # hilum: surface nodes on the medial (+y) face, ~5-15% of the surface
    assert np.all(np.isin(hilum, surf))
    assert 0.05 <= len(hilum) / len(surf) <= 0.15, len(hilum) / len(surf)
    assert normals[hilum, 1].mean() > 0.5
    hc = mesh.landmarks["hilum_center"]
    np.testing.assert_allclose(hc, mesh.nodes[hilum].mean(axis=0))
    assert hc[1] > 0
    # indented: the hilum lies clearly below the most medial rim of the crescent
    assert hc[1] < mesh.nodes[:, 1].max() - 0.002

    axis = mesh.landmarks["inferior_pole_axis"]
    tip = mesh.landmarks["inferior_pole_tip"]
    assert abs(np.linalg.norm(axis) - 1.0) < 1e-12
    assert axis[0] > 0.8 and axis[1] > 0  # along +x, tilted toward the medial side
    # the tip is the extreme point along the axis (within one cell, PL surface)
    proj = (mesh.nodes - tip) @ axis
    assert proj.max() < 0.005
    assert tip[0] > 0.9 * mesh.nodes[:, 0].max()
    pole = mesh.node_sets["inferior_pole"]
    depth = (tip - mesh.nodes) @ axis
    np.testing.assert_array_equal(pole, np.flatnonzero(depth <= 0.04))
    assert np.any(~np.isin(pole, surf))  # interior nodes included
    assert mesh.nodes[pole, 0].min() > 0  # pole is the +x (inferior) end


def test_spleen_medial_face_concave_and_lateral_convex():
    mesh = get_mesh("spleen", "medium")
    p = mesh.nodes
    s = mesh.surface_nodes
    mid = s[np.abs(p[s, 2]) < 0.004]
    x, y = p[mid, 0], p[mid, 1]
    medial_centre = y[(np.abs(x) < 0.005)].max()
    medial_side = y[(np.abs(x) > 0.02) & (np.abs(x) < 0.04)].max()
    assert medial_centre < medial_side  # crescent + hilum: concave medial face
    assert y.min() == pytest.approx(p[:, 1].min())  # lateral face bulges at the middle


def test_spleen_options_and_errors():
    m = spleen_mesh("coarse", volume_m3=100e-6)
    assert m.volume == pytest.approx(100e-6, rel=1e-9)
    straight = spleen_mesh("coarse", bend=0.0, hilum_depth=0.0)
    assert abs(straight.landmarks["inferior_pole_axis"][1]) < 1e-9
    with pytest.raises(MeshError, match="length_m"):
        spleen_mesh(length_m=-1.0)
    with pytest.raises(MeshError, match="hilum_depth"):
        spleen_mesh(hilum_depth=1.5)


@pytest.mark.parametrize("pattern", GRID_PATTERNS)
def test_every_grid_pattern_is_a_conforming_split_of_the_box(pattern):
    shape = (5, 4, 3)
    box, tets = kuhn_box(shape, pattern)
    vol = np.abs(np.linalg.det(box[tets[:, 1:]] - box[tets[:, :1]])) / 6.0
    assert vol.sum() == pytest.approx(8.0, rel=1e-12) and vol.min() > 0  # ([-1, 1]^3, nothing inverted)
    # conforming: every triangle is shared by two tets or lies on the box's surface
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]], tets[:, [0, 1, 2]]]),
                    axis=1)
    uniq, count = np.unique(faces, axis=0, return_counts=True)
    on_box = np.any(np.all(np.isclose(np.abs(box[uniq]), 1.0), axis=1) & (np.ptp(box[uniq], axis=1) == 0), axis=1)
    assert set(count[~on_box]) == {2} and set(count[on_box]) == {1}
    # the lattice is the grid's own coordinates, node for node
    assert np.allclose(box, 2.0 * kuhn_lattice(shape) / np.asarray(shape) - 1.0)


def test_the_shell_pattern_splits_the_spleen_s_grid_without_a_sliver_where_the_alternating_grid_fails():
    with pytest.raises(MeshError, match="degenerate tet"):
        spleen_on_grid("medium", "alternating")
    octant, shell = spleen_mesh("medium"), spleen_on_grid("medium")
    assert np.array_equal(shell.nodes, octant.nodes) and len(spleen_lattice("medium")) == octant.n_nodes
    # the same body: its volume moves only by the surface quads' other split
    assert shell.volume == pytest.approx(octant.volume, rel=1e-3)
    assert np.array_equal(shell.surface_nodes, octant.surface_nodes)
    with pytest.raises(MeshError, match="pattern"):
        spleen_on_grid("coarse", "diagonal")


@pytest.mark.parametrize("kind", ["sphere", "spleen"])
def test_deterministic(kind):
    fn = sphere_mesh if kind == "sphere" else spleen_mesh
    a, b = fn(resolution="coarse"), fn(resolution="coarse")
    np.testing.assert_array_equal(a.nodes, b.nodes)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.surface_tris, b.surface_tris)
    assert a.node_sets.keys() == b.node_sets.keys() and a.landmarks.keys() == b.landmarks.keys()
    for k in a.node_sets:
        np.testing.assert_array_equal(a.node_sets[k], b.node_sets[k])
    for k in a.landmarks:
        np.testing.assert_array_equal(a.landmarks[k], b.landmarks[k])


# ------------------------------------------------------------------------------------------
# Resolution handling, TetMesh API
# ------------------------------------------------------------------------------------------


def test_resolution_int_and_errors():
    m = sphere_mesh(resolution=500)
    assert abs(m.n_nodes / 500 - 1) <= 0.15
    with pytest.raises(MeshError, match="resolution") as exc:
        sphere_mesh(resolution="huge")
    assert "coarse" in str(exc.value) and "xfine" in str(exc.value)
    with pytest.raises(ValueError, match="resolution"):
        spleen_mesh(resolution=5)
    with pytest.raises(MeshError):
        sphere_mesh(resolution=True)
    assert sphere_mesh(resolution="Coarse").n_nodes == get_mesh("sphere", "coarse").n_nodes


def test_summary_and_readonly():
    mesh = get_mesh("spleen", "coarse")
    s = mesh.summary()
    for key in ("n_nodes", "n_tets", "n_edges", "n_surface_nodes", "volume_m3", "bbox_m", "min_quality",
                "mean_quality", "node_sets"):
        assert key in s
    assert s["n_nodes"] == mesh.n_nodes and s["n_edges"] == len(mesh.edges)
    assert len(s["bbox_m"]) == 3 and s["node_sets"]["hilum"] == len(mesh.node_sets["hilum"])
    assert isinstance(s["min_quality"], float)
    with pytest.raises(ValueError):
        mesh.nodes[0, 0] = 1.0  # cached derived data must not go stale
    assert "spleen" in repr(mesh)


def test_quality_reference_values():
    reg = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    assert tet_quality(reg, np.array([[0, 1, 3, 2]]))[0] == pytest.approx(1.0, abs=1e-12)
    # Kuhn (path) tet of a unit cube: 3 r_in / r_circ = 0.7174
    kuhn = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1]], dtype=float)
    assert tet_quality(kuhn, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(0.7174, abs=1e-4)


def test_node_sets_and_landmarks_validated():
    nodes, tets = unit_tet_nodes(), np.array([[0, 1, 2, 3]])
    m = TetMesh(nodes, tets, node_sets={"a": [3, 1, 1]}, landmarks={"p": (1, 2, 3)})
    np.testing.assert_array_equal(m.node_sets["a"], [1, 3])
    with pytest.raises(MeshError, match="node set 'b'.*7"):
        TetMesh(nodes, tets, node_sets={"b": [7]})
    with pytest.raises(MeshError, match="landmark 'q'"):
        TetMesh(nodes, tets, landmarks={"q": (1.0, np.nan, 0.0)})


# ------------------------------------------------------------------------------------------
# Validation errors
# ------------------------------------------------------------------------------------------


def test_all_negative_orientation_is_flipped():
    mesh = get_mesh("sphere", "coarse")
    flipped = mesh.tets[:, [1, 0, 2, 3]]
    m = TetMesh(mesh.nodes, flipped)
    assert np.all(m.tet_volumes > 0)
    assert m.volume == pytest.approx(mesh.volume, rel=1e-12)


def test_mixed_orientation_names_inverted_tet():
    mesh = get_mesh("sphere", "coarse")
    tets = mesh.tets.copy()
    tets[5] = tets[5][[1, 0, 2, 3]]
    with pytest.raises(MeshError, match=r"tet 5 is inverted"):
        validate_tets(mesh.nodes, tets, source="probe")


def test_nan_coordinate_names_node():
    nodes = unit_tet_nodes()
    nodes[2, 1] = np.nan
    with pytest.raises(MeshError, match=r"node 2 .*NaN"):
        TetMesh(nodes, np.array([[0, 1, 2, 3]]))


def test_degenerate_tet_names_tet_and_quality():
    nodes = np.vstack([unit_tet_nodes(), [[1.0, 1.0, 0.0]]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 2]])  # second tet lies flat in z = 0
    with pytest.raises(MeshError, match=r"degenerate tet 1 .*quality"):
        validate_tets(nodes, tets)
    # a sliver: nearly flat but non-zero volume
    nodes[4, 2] = 1e-6
    with pytest.raises(MeshError, match=r"degenerate tet 1"):
        validate_tets(nodes, tets)


def test_disconnected_pieces():
    nodes = np.vstack([unit_tet_nodes(), unit_tet_nodes() + 5.0])
    tets = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    with pytest.raises(MeshError, match=r"not connected: 2 pieces.*\[1, 1\]") as exc:
        validate_tets(nodes, tets, source="twotets")
    assert "twotets" in str(exc.value) and "[0, 1]" in str(exc.value)


@pytest.mark.parametrize(
    "nodes,tets,pattern",
    [
        (unit_tet_nodes(), np.zeros((0, 4), dtype=int), "no tetrahedra"),
        (unit_tet_nodes(), np.array([[0, 1, 2, 9]]), r"tet 0 references node 9"),
        (unit_tet_nodes(), np.array([[0, 1, 2, -1]]), r"tet 0 references node -1"),
        (unit_tet_nodes(), np.array([[0, 1, 1, 3]]), r"tet 0 repeats a node"),
        (unit_tet_nodes(), np.array([[0.0, 1.0, 2.0, 3.0]]), "integer"),
        (unit_tet_nodes(), np.array([[0, 1, 2]]), r"shape \(T,4\)"),
        (unit_tet_nodes()[:, :2], np.array([[0, 1, 2, 3]]), r"shape \(N,3\)"),
        (np.vstack([unit_tet_nodes(), [[9.0, 9.0, 9.0]]]), np.array([[0, 1, 2, 3]]), r"node 4 is not used"),
    ],
)
def test_validation_errors(nodes, tets, pattern):
    with pytest.raises(MeshError, match=pattern):
        validate_tets(nodes, tets)


def test_overlapping_tets_rejected():
    # two tets on the same side of a shared face
    nodes = np.vstack([unit_tet_nodes(), [[0.2, 0.2, 0.5]]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])
    with pytest.raises(MeshError, match=r"tetrahedra 0 and 1 overlap"):
        validate_tets(nodes, tets)


# ------------------------------------------------------------------------------------------
# File I/O
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix,fmt", [(".vtu", None), (".msh", None), (".msh", "gmsh22"), (".vtk", None)])
def test_save_load_round_trip(tmp_path, suffix, fmt):
    mesh = get_mesh("spleen", "coarse")
    path = tmp_path / f"organ{suffix}"
    save_mesh(mesh, path, file_format=fmt)
    back = load_mesh(path)
    np.testing.assert_allclose(back.nodes, mesh.nodes, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    for key, ids in mesh.node_sets.items():
        np.testing.assert_array_equal(back.node_sets[key], ids)
    assert back.name == "organ"
    assert sorted(os.listdir(tmp_path)) == [path.name]  # atomic: no temp files left behind


def test_save_overwrites_and_build_mesh_from_path(tmp_path):
    path = tmp_path / "s.vtu"
    save_mesh(get_mesh("spleen", "coarse"), path)
    save_mesh(get_mesh("sphere", "coarse"), path)
    m = build_mesh(str(path))
    assert m.n_nodes == get_mesh("sphere", "coarse").n_nodes
    assert build_mesh(path).n_tets == m.n_tets  # PathLike too
    with pytest.raises(MeshError, match="only apply to the built-in"):
        build_mesh(str(path), diameter_m=0.1)
    with pytest.raises(MeshError, match="does not exist"):
        save_mesh(m, tmp_path / "missing_dir" / "x.vtu")


def test_build_mesh_builtins():
    assert build_mesh("sphere").n_nodes == get_mesh("sphere", "coarse").n_nodes
    sp = build_mesh("Spleen", "medium")
    np.testing.assert_array_equal(sp.nodes, get_mesh("spleen", "medium").nodes)
    small = build_mesh("sphere", diameter_m=0.01)
    assert np.ptp(small.nodes[:, 0]) <= 0.01


def test_load_missing_file(tmp_path):
    path = tmp_path / "nope.vtu"
    with pytest.raises(MeshError, match="not found") as exc:
        load_mesh(path)
    assert str(path) in str(exc.value)


def test_load_unknown_extension(tmp_path):
    path = tmp_path / "mesh.foo"
    path.write_text("hello")
    with pytest.raises(MeshError, match="format") as exc:
        load_mesh(path)
    assert str(path) in str(exc.value)


def test_load_only_triangles(tmp_path):
    path = tmp_path / "tris.vtu"
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    meshio.write(path, meshio.Mesh(pts, [("triangle", tris)]))
    with pytest.raises(MeshError, match="no 'tetra' cells.*triangle x 4") as exc:
        load_mesh(path)
    assert str(path) in str(exc.value)


def test_load_ignores_surface_cells(tmp_path):
    mesh = get_mesh("sphere", "coarse")
    path = tmp_path / "mixed.msh"
    cells = [("triangle", mesh.surface_tris), ("tetra", mesh.tets)]
    meshio.write(path, meshio.Mesh(mesh.nodes, cells), file_format="gmsh22")
    back = load_mesh(path)
    np.testing.assert_array_equal(back.tets, mesh.tets)


def test_load_nan_and_inverted_file(tmp_path):
    nodes, tets = get_mesh("sphere", "coarse").nodes.copy(), get_mesh("sphere", "coarse").tets.copy()
    bad = nodes.copy()
    bad[7] = np.nan
    p1 = tmp_path / "nan.vtu"
    meshio.write(p1, meshio.Mesh(bad, [("tetra", tets)]))
    with pytest.raises(MeshError, match=r"node 7 .*NaN") as exc:
        load_mesh(p1)
    assert str(p1) in str(exc.value)
    mixed = tets.copy()
    mixed[3] = mixed[3][[0, 2, 1, 3]]
    p2 = tmp_path / "mixed.vtu"
    meshio.write(p2, meshio.Mesh(nodes, [("tetra", mixed)]))
    with pytest.raises(MeshError, match=r"tet 3 is inverted"):
        load_mesh(p2)
    # all tets negatively oriented (a file convention): flipped silently
    p3 = tmp_path / "neg.vtu"
    meshio.write(p3, meshio.Mesh(nodes, [("tetra", tets[:, [0, 2, 1, 3]])]))
    assert np.all(load_mesh(p3).tet_volumes > 0)


def test_load_unused_node_file(tmp_path):
    nodes = np.vstack([unit_tet_nodes(), [[3.0, 3.0, 3.0]]])
    path = tmp_path / "unused.vtu"
    meshio.write(path, meshio.Mesh(nodes, [("tetra", np.array([[0, 1, 2, 3]]))]))
    with pytest.raises(MeshError, match=r"node 4 is not used"):
        load_mesh(path)


def test_pickle_round_trip_keeps_readonly():
    import pickle

    mesh = get_mesh("spleen", "coarse")
    back = pickle.loads(pickle.dumps(mesh))
    np.testing.assert_array_equal(back.surface_tris, mesh.surface_tris)
    assert back.volume == mesh.volume and not back.nodes.flags.writeable
    assert not back.node_sets["hilum"].flags.writeable


# -- the evenly sampled sphere (shipped gmsh meshes) -------------------------------------------------

EVEN_NODES = {"coarse": 256, "medium": 1011, "fine": 3328}


@pytest.mark.parametrize("resolution", list(EVEN_NODES))
def test_even_sphere_is_sampled_on_the_sphere_with_a_node_at_each_pole(resolution):
    """The shipped gmsh meshes: every surface node on the sphere, one at each pole (no flat polar facet),
    valid tets of fair quality, and the diameter / centre options of the mapped-box generator."""
    m = build_mesh("sphere-even", resolution, diameter_m=0.04, center=(0.01, 0.0, 0.0))
    assert m.n_nodes == EVEN_NODES[resolution]
    r = np.linalg.norm(m.nodes[m.surface_nodes] - [0.01, 0.0, 0.0], axis=1)
    np.testing.assert_allclose(r, 0.02, rtol=1e-9)
    z = m.nodes[m.surface_nodes, 2]
    assert z.max() == pytest.approx(0.02, rel=1e-9) and z.min() == pytest.approx(-0.02, rel=1e-9)
    assert np.count_nonzero(z > 0.02 - 1e-9) == 1  # a single pole node, not a facet
    assert tet_quality(m.nodes, m.tets).min() > 0.25  # measured 0.49 / 0.36 / 0.30


def test_even_sphere_resolutions_are_the_shipped_ones():
    with pytest.raises(MeshError, match="not available for 'sphere-even'.*coarse"):
        build_mesh("sphere-even", 500)
    with pytest.raises(MeshError, match="diameter_m"):
        build_mesh("sphere-even", "coarse", diameter_m=-1.0)


def test_even_sphere_contact_is_hertzian_and_converges():
    """Static plate compression of the linear van Gelder network (E = 60 kPa): on the evenly sampled
    surface the small-strain force exponent (1-7 mm of travel) is Hertz's 1.5 +/- 0.15 already on the
    coarse mesh (the mapped box's flat facet gives 1.00). The force at 10 % compression (5 mm) differs by
    11 % between the coarse and fine raw networks (the mapped box: 3.11 vs ~1.8 N, 70 %), and by less than
    10 % once each is Hertz-calibrated as configs/tissue/sphere.yaml does (measured 1.5 %)."""
    from msdgrasp.physics.tissue import TissueModel, TissueParams, plate_compression_force

    raw = TissueParams(youngs_modulus_pa=60e3)
    calibrated = TissueParams(youngs_modulus_pa=60e3, contact_calibration="hertz")

    def force(mesh, depth, params=raw):
        k1 = TissueModel.from_params(mesh, params).k1
        return plate_compression_force(mesh.nodes, mesh.edges, k1, mesh.surface_nodes, depth, max_iter=400)[0]

    coarse, fine = build_mesh("sphere-even", "coarse"), build_mesh("sphere-even", "fine")
    d = np.linspace(1e-3, 7e-3, 7)
    n = np.polyfit(np.log(d), np.log([force(coarse, x) for x in d]), 1)[0]
    assert n == pytest.approx(1.5, abs=0.15)
    assert abs(force(coarse, 0.005) / force(fine, 0.005) - 1.0) < 0.15
    assert abs(force(coarse, 0.005, calibrated) / force(fine, 0.005, calibrated) - 1.0) < 0.10


# -- the spleen filled with unstructured tets (shipped gmsh meshes) -------------------------------------------


@pytest.mark.parametrize("resolution", ["coarse", "medium", "fine"])
def test_even_spleen_is_the_built_in_spleens_surface_filled_anew(resolution):
    """The same organ as the built-in grid: its surface nodes and triangles, its volume, node sets and landmarks;
    only the interior differs (fewer nodes, no grid), with valid tets of fair quality."""
    from msdgrasp.physics.mesh import boundary_faces

    grid, even = build_mesh("spleen", resolution), build_mesh("spleen-even", resolution)
    surf = grid.node_sets["surface"]
    np.testing.assert_array_equal(even.node_sets["surface"], np.arange(len(surf)))
    np.testing.assert_allclose(even.nodes[: len(surf)], grid.nodes[surf], rtol=0, atol=1e-12)
    renumber = np.full(grid.n_nodes, -1)
    renumber[surf] = np.arange(len(surf))
    tri = lambda t: {tuple(sorted(f)) for f in t.tolist()}  # noqa: E731
    assert tri(boundary_faces(even.tets, "even")) == tri(renumber[boundary_faces(grid.tets, "grid")])
    assert even.volume == pytest.approx(grid.volume, rel=1e-12)
    assert even.n_nodes < grid.n_nodes
    np.testing.assert_array_equal(even.nodes[even.node_sets["hilum"]], grid.nodes[grid.node_sets["hilum"]])
    assert set(even.landmarks) == set(grid.landmarks)
    tip, axis = even.landmarks["inferior_pole_tip"], even.landmarks["inferior_pole_axis"]
    pole = even.node_sets["inferior_pole"]
    assert pole.size and ((tip - even.nodes[pole]) @ axis).max() <= 0.04
    assert tet_quality(even.nodes, even.tets).min() > 0.2  # measured 0.32 / 0.24 / 0.31 (the grid's 0.43 / 0.39 / 0.33)


def test_even_spleen_resolutions_are_the_shipped_ones():
    with pytest.raises(MeshError, match="not available for 'spleen-even'.*coarse"):
        build_mesh("spleen-even", "xfine")


def test_the_shipped_gmsh_meshes_are_what_msdgrasp_meshes_makes(capsys):
    """`msdgrasp meshes --check` regenerates every shipped gmsh mesh in memory: the same tets, nodes within 1e-12 m
    (deterministic for the recorded gmsh version)."""
    gmsh = pytest.importorskip("gmsh")
    from msdgrasp.cli.main import main
    from msdgrasp.meshes.generate import GMSH_VERSION

    if gmsh.__version__ != GMSH_VERSION:
        pytest.skip(f"the shipped meshes were made with gmsh {GMSH_VERSION}")
    assert main(["meshes", "--check"]) == 0
    assert "DIFFERS" not in capsys.readouterr().out
