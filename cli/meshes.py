"""``msdgrasp meshes [--check]``: regenerate the shipped gmsh meshes (msdgrasp/meshes), or compare them with a fresh
generation. Needs gmsh (``pip install -e ".[meshing]"``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

import numpy as np

from ..meshes import MESH_DIR
from ..meshes import generate as gen
from ..physics.config import require_extra
from ..physics.mesh import boundary_faces
from ..physics.mesh_gen import spleen_mesh
from ..physics.mesh_io import surface_first


def _spleen_fill(resolution: str) -> tuple[np.ndarray, np.ndarray]:
    """The built-in spleen's surface at ``resolution`` (its surface nodes in id order) filled by gmsh."""
    grid = spleen_mesh(resolution)
    return gen.fill_surface(grid.nodes[grid.node_sets["surface"]],
                            surface_first(grid)[boundary_faces(grid.tets, "spleen")])


def jobs() -> list[tuple[str, Callable[[], tuple[np.ndarray, np.ndarray]]]]:
    """(file name, its generator) of every shipped gmsh mesh."""
    out = [(f"sphere_{name}.vtu", lambda size=size: gen.sphere_points_and_tets(size))
           for name, size in gen.SIZES.items()]
    return out + [(f"spleen_even_{res}.vtu", lambda res=res: _spleen_fill(res)) for res in gen.SPLEEN_RESOLUTIONS]


def meshes_cli(args: argparse.Namespace) -> int:
    import meshio

    require_extra("meshing", "msdgrasp meshes", "gmsh")
    import gmsh

    if gmsh.__version__ != gen.GMSH_VERSION:
        print(f"warning: gmsh {gmsh.__version__}, the shipped files were made with {gen.GMSH_VERSION}", file=sys.stderr)
    bad = 0
    made = []
    for filename, make in jobs():  # (every mesh made before any file is written: a failure leaves the set whole)
        nodes, tets = make()
        made.append((MESH_DIR / filename, nodes, gen.orient(nodes, tets)))
    for path, nodes, tets in made:
        if args.check:
            ref = meshio.read(path)
            ref_tets = np.concatenate([c.data for c in ref.cells if c.type == "tetra"])
            same = ref.points.shape == nodes.shape and np.array_equal(ref_tets, tets) \
                and np.allclose(ref.points, nodes, rtol=0.0, atol=1e-12)
            bad += not same
            print(f"{path.name}: {'same' if same else 'DIFFERS'} ({len(nodes)} nodes, {len(tets)} tets)")
        else:
            tmp = path.with_name(f".{path.name}.tmp")
            meshio.write(tmp, meshio.Mesh(nodes, [("tetra", tets)]), file_format="vtu")
            tmp.replace(path)  # atomic
            print(f"wrote {path} ({len(nodes)} nodes, {len(tets)} tets)")
    return 1 if bad else 0
