"""Mesh files through meshio: :func:`load_mesh` (validated, with named node sets), :func:`save_mesh`
(atomic) and :func:`build_mesh` (a built-in mesh by name, or a file).
"""

from __future__ import annotations

import contextlib
import inspect
import io
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .config import TISSUE_FILE, ConfigError, atomic_write, read_config_file
from .mesh import MeshError, TetMesh
from .mesh_gen import sphere_mesh, spleen_mesh, spleen_on_grid

__all__ = ["MeshSpec", "load_mesh", "save_mesh", "build_mesh", "mesh_from_config", "mesh_spec"]



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
    said = io.StringIO()  # (meshio prints some of its errors before it exits: they go into ours, one line)
    try:
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(p)
    except meshio.ReadError as exc:
        raise MeshError(f"cannot read mesh file {p} (unknown or unsupported format?): {exc}") from exc
    except (Exception, SystemExit) as exc:  # meshio raises assorted errors on malformed files, some sys.exit(1)
        why = " ".join((said.getvalue() or f"{type(exc).__name__}: {exc}").split())
        raise MeshError(f"cannot read mesh file {p}: {why}") from None

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


#: the built-in sphere with an evenly sampled surface (shipped gmsh meshes, msdgrasp/meshes)
SPHERE_EVEN = "sphere-even"


def sphere_even_mesh(diameter_m: float = 0.05, resolution: str = "coarse", center=(0.0, 0.0, 0.0)) -> TetMesh:
    """The solid sphere meshed by gmsh (:mod:`msdgrasp.meshes.generate`): a node at each pole and even rings
    around it, so plates and jaws meet a curved surface at every resolution (the mapped box of
    :func:`.mesh_gen.sphere_mesh` has a flat 4-node facet at each pole). Shipped at ``coarse`` (256 nodes),
    ``medium`` (1011) and ``fine`` (3328), made at 50 mm and scaled to ``diameter_m``."""
    from ..meshes import MESH_DIR
    from ..meshes.generate import RADIUS_M, SIZES

    if not isinstance(resolution, str) or resolution.strip().lower() not in SIZES:
        raise MeshError(f"resolution={resolution!r} is not available for '{SPHERE_EVEN}'; allowed: {list(SIZES)} "
                        "(shipped meshes; add a size to msdgrasp/meshes/generate.py and run msdgrasp meshes for more)")
    if not (isinstance(diameter_m, (int, float)) and np.isfinite(diameter_m) and diameter_m > 0):
        raise MeshError(f"diameter_m must be a number > 0, got {diameter_m!r}")
    base = load_mesh(MESH_DIR / f"sphere_{resolution.strip().lower()}.vtu")
    nodes = base.nodes * (0.5 * float(diameter_m) / RADIUS_M) + np.asarray(center, dtype=np.float64)
    return TetMesh(nodes, base.tets, name=f"{SPHERE_EVEN}-{resolution.strip().lower()}")


#: the built-in spleen's surface filled with unstructured tets (shipped gmsh meshes, msdgrasp/meshes)
SPLEEN_EVEN = "spleen-even"
#: the built-in spleen's nodes on the J1 split with outward boundary cells (:func:`spleen_j1_mesh`)
SPLEEN_J1 = "spleen-j1"


def surface_first(mesh: TetMesh) -> np.ndarray:
    """Per node of ``mesh``, its index when its surface nodes come first in id order (-1 for the interior): how a
    surface is handed to gmsh and how ``spleen-even`` numbers the built-in spleen's surface."""
    surf = mesh.node_sets["surface"]
    index = np.full(mesh.n_nodes, -1, dtype=np.int64)
    index[surf] = np.arange(len(surf))
    return index


def spleen_even_mesh(resolution: str = "coarse") -> TetMesh:
    """The built-in spleen (:func:`.mesh_gen.spleen_mesh` at its default shape) with the same surface nodes and
    triangles, its interior filled by gmsh's Delaunay tets (:mod:`msdgrasp.meshes.generate`) instead of the mapped Kuhn
    grid, whose spring network is anisotropic (docs/validation.md). Node sets and landmarks are the built-in mesh's:
    its surface nodes are this mesh's first ones, in the same order; ``inferior_pole`` by the same rule. Shipped at
    ``coarse`` (190 nodes), ``medium`` (610) and ``fine`` (2019)."""
    from ..meshes import MESH_DIR
    from ..meshes.generate import SPLEEN_RESOLUTIONS

    key = resolution.strip().lower() if isinstance(resolution, str) else None
    if key not in SPLEEN_RESOLUTIONS:
        raise MeshError(f"resolution={resolution!r} is not available for '{SPLEEN_EVEN}'; allowed: "
                        f"{list(SPLEEN_RESOLUTIONS)} (shipped meshes, made by msdgrasp meshes with gmsh)")
    base = load_mesh(MESH_DIR / f"spleen_even_{key}.vtu")
    grid = spleen_mesh(key)
    surf = grid.node_sets["surface"]
    if not np.allclose(base.nodes[: len(surf)], grid.nodes[surf], rtol=0.0, atol=1e-12):
        raise MeshError(f"{MESH_DIR / f'spleen_even_{key}.vtu'}: its first nodes are not the built-in spleen's "
                        "surface; regenerate it with msdgrasp meshes")
    renumber = surface_first(grid)
    tip, axis = grid.landmarks["inferior_pole_tip"], grid.landmarks["inferior_pole_axis"]
    pole_length = inspect.signature(spleen_mesh).parameters["pole_length_m"].default  # (the built-in mesh's rule)
    sets = {"surface": np.arange(len(surf)), "hilum": renumber[grid.node_sets["hilum"]],
            "inferior_pole": np.flatnonzero((tip - base.nodes) @ axis <= pole_length)}
    return TetMesh(base.nodes, base.tets, node_sets=sets, landmarks=dict(grid.landmarks), name=f"{SPLEEN_EVEN}-{key}")


def spleen_j1_mesh(resolution: str | int = "coarse") -> TetMesh:
    """The built-in spleen's nodes, node sets and landmarks on the J1 split whose boundary cells point outward
    (:func:`.mesh_gen.spleen_on_grid` with ``"alternating-shell"``): a spring network that converges to the continuum
    (docs/validation.md)."""
    return spleen_on_grid(resolution, "alternating-shell")


#: the built-in mesh generators by ``shape`` name (any other shape is a mesh file)
GENERATORS = {"sphere": sphere_mesh, SPHERE_EVEN: sphere_even_mesh, "spleen": spleen_mesh,
              SPLEEN_EVEN: spleen_even_mesh, SPLEEN_J1: spleen_j1_mesh}


def build_mesh(spec: str | os.PathLike, resolution: str | int = "coarse", **kwargs) -> TetMesh:
    """Build a mesh from a spec: a built-in shape (:data:`GENERATORS`: ``"sphere"``, a mapped box; ``"sphere-even"``,
    gmsh, evenly sampled surface; ``"spleen"``, ``"spleen-even"``, ``"spleen-j1"``) or a mesh file path.

    ``resolution`` and ``kwargs`` go to the built-in generator; for a file path the resolution
    is ignored and keyword options are an error.
    """
    key = str(spec).strip().lower() if isinstance(spec, str) else None
    if key in GENERATORS:
        return GENERATORS[key](resolution=resolution, **kwargs)
    if kwargs:
        raise MeshError(
            f"options {sorted(kwargs)} only apply to the built-in meshes {', '.join(map(repr, GENERATORS))}, "
            f"not to the mesh file {spec!s}"
        )
    return load_mesh(spec)


class MeshSpec(NamedTuple):
    """A tissue config's ``mesh:`` section, checked: a built-in shape (its generator's options) or a mesh
    file (an absolute path: a relative one is read from the folder of the YAML that names it)."""

    #: a built-in shape (:data:`GENERATORS`) or the absolute path of a mesh file
    shape: str
    #: the generator's resolution (None: the generator's default; unused for a file)
    resolution: str | int | None
    #: the generator's other options (sizes in m)
    options: dict[str, Any]

    @property
    def is_file(self) -> bool:
        return self.shape not in GENERATORS

    def build(self, resolution: str | int | None = None, **overrides: Any) -> TetMesh:
        """The mesh; ``resolution`` and ``overrides`` replace the section's values (built-in shapes only)."""
        if self.is_file:
            if overrides:
                raise MeshError(f"options {sorted(overrides)} only apply to the built-in meshes, not to the mesh "
                                f"file {self.shape}")
            return load_mesh(self.shape)
        res = resolution if resolution is not None else self.resolution
        kwargs = {**self.options, **overrides}
        return GENERATORS[self.shape](**({"resolution": res} if res is not None else {}), **kwargs)


def _own_mesh_file(data: dict[str, Any], file: Path) -> dict[str, Any]:
    """A tissue config's own ``mesh.shape``, where it names a mesh file (not a built-in shape), as an absolute path
    read from that config's folder: through ``extends`` a parent's mesh file stays the one beside the parent."""
    mesh = data.get("mesh")
    shape = mesh.get("shape") if isinstance(mesh, dict) else None
    if not isinstance(shape, str) or not shape.strip() or shape.strip().lower() in GENERATORS:
        return data
    return {**data, "mesh": {**mesh, "shape": str((file.resolve().parent / Path(shape).expanduser()))}}


def mesh_spec(path: str | os.PathLike) -> MeshSpec:
    """The checked ``mesh:`` section of tissue config ``path``: the file must have it (no shape is assumed),
    ``shape`` is required, every other key must be an option of that shape's generator, and a mesh file
    must exist (a relative path is taken from the YAML's folder, so a config and its mesh move together).
    Every error is one :class:`ConfigError` line naming the YAML and the key or the path."""
    section = dict(read_config_file(path, TISSUE_FILE, _own_mesh_file)["mesh"])
    where = f"{path}:mesh"
    gens = GENERATORS
    if "shape" not in section:
        raise ConfigError(f"{where}.shape is required: one of {', '.join(gens)} or a mesh file (relative to the "
                          "YAML's folder)")
    shape = section.pop("shape")
    if not isinstance(shape, str) or not shape.strip():
        raise ConfigError(f"{where}.shape must be one of {', '.join(gens)} or a mesh file path, got {shape!r}")
    key = shape.strip().lower()
    if key in gens:
        params = inspect.signature(gens[key]).parameters
        allowed = sorted(["shape", *params])
        for name in section:
            if name not in params:
                raise ConfigError(f"{where}: unknown key {name!r} for shape {key!r}; "
                                  f"allowed keys: {', '.join(allowed)}")
        resolution = section.pop("resolution", None)
        return MeshSpec(key, resolution, section)
    if section:
        raise ConfigError(f"{where}: unknown key {next(iter(section))!r} for a mesh file (shape {shape!r}); a mesh "
                          f"file takes no options; allowed keys: shape")
    file = Path(shape)  # (absolute: _own_mesh_file)
    if not file.is_file():
        raise ConfigError(f"{where}.shape: mesh file not found: {file} (not a built-in shape: {', '.join(gens)}; "
                          "a relative path is read from the YAML's folder)")
    return MeshSpec(str(file), None, {})


def mesh_from_config(path: str | os.PathLike, resolution: str | int | None = None) -> TetMesh:
    """The mesh of a tissue config's ``mesh:`` section (:func:`mesh_spec`); ``resolution`` overrides the
    config's."""
    return mesh_spec(path).build(resolution)
