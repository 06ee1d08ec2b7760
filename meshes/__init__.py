"""Shipped tetrahedral meshes (data): the test sphere with an evenly sampled surface, made by gmsh.

The files are built by :mod:`msdgrasp.meshes.generate` (gmsh, an optional dependency:
``pip install -e ".[meshing]"``) and read with meshio like any mesh file; the physics loads them through
``build_mesh("sphere-even", resolution)``.
"""

from pathlib import Path

MESH_DIR = Path(__file__).resolve().parent
