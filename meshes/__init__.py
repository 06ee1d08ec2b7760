"""Shipped tetrahedral meshes (data), made by gmsh: the test sphere with an evenly sampled surface, and the built-in
spleen's surface filled with unstructured tets.

The files are built by ``msdgrasp meshes`` (how: :mod:`msdgrasp.meshes.generate`; gmsh is an optional dependency,
``pip install -e ".[meshing]"``) and read with meshio like any mesh file; the physics loads them through
``build_mesh("sphere-even", resolution)`` and ``build_mesh("spleen-even", resolution)``.
"""

from pathlib import Path

MESH_DIR = Path(__file__).resolve().parent
