"""Nodal normal stress as the paper defines it (Fig. 8).

"This stress was computed for each node as the normal component of the total inter-nodal force vector,
acting on that node, divided by the area of the polygon formed between the mid points of its inter-nodal
springs."

* Surface nodes: the normal is the outward vertex normal of the deformed surface; the polygon through the
  midpoints of the node's surface edges has area sum(A_tri)/4 over its surface triangles.
* Any node, given a section normal ``direction`` (e.g. the lateral cross-section of the paper's Fig. 8):
  the force is projected on ``direction`` and the polygon is the convex hull of its springs' midpoints
  projected onto the section plane.

Sign convention: positive = compressive (the springs push the node outward through the surface, as under
a jaw that presses on it); negative = tensile.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .tissue import TissueModel


def surface_normal_stress(model: TissueModel, x: np.ndarray, stiffness_scale: float = 1.0) -> np.ndarray:
    """(N,) normal stress (Pa) at surface nodes of configuration ``x``; 0 at interior nodes."""
    f = model.internal_forces(x, stiffness_scale=stiffness_scale)
    normals = model.mesh.vertex_normals(x)
    area = model.mesh.surface_vertex_areas(x)
    out = np.zeros(model.n_nodes)
    s = area > 0
    out[s] = np.einsum("ij,ij->i", f[s], normals[s]) / area[s]
    return out


def section_normal_stress(
    model: TissueModel, x: np.ndarray, direction, nodes: np.ndarray | None = None, stiffness_scale: float = 1.0
) -> np.ndarray:
    """(len(nodes),) normal stress (Pa) on the section plane with unit normal ``direction``.

    Stress = (F_int . d) / A, with A the convex-hull area of the node's spring midpoints projected on the
    plane normal to d. With d the outward normal this is the surface convention (compressive positive).
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    f = model.internal_forces(x, stiffness_scale=stiffness_scale)
    nodes = np.arange(model.n_nodes) if nodes is None else np.asarray(nodes)
    # orthonormal basis of the section plane
    t1 = np.cross(d, [1.0, 0.0, 0.0])
    if np.linalg.norm(t1) < 1e-6:
        t1 = np.cross(d, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(d, t1)
    edges = model.edges
    mid = 0.5 * (x[edges[:, 0]] + x[edges[:, 1]])
    order = np.argsort(np.concatenate([edges[:, 0], edges[:, 1]]), kind="stable")
    owner = np.concatenate([edges[:, 0], edges[:, 1]])[order]
    mids = np.concatenate([mid, mid])[order]
    starts = np.searchsorted(owner, np.arange(model.n_nodes + 1))
    out = np.empty(len(nodes))
    for k, i in enumerate(nodes):
        pts = mids[starts[i] : starts[i + 1]] - x[i]
        p2 = np.stack([pts @ t1, pts @ t2], axis=1)
        try:
            area = ConvexHull(p2).volume  # in 2-D, "volume" is the area
        except (QhullError, ValueError):
            area = 0.0
        out[k] = (f[i] @ d) / area if area > 0 else 0.0
    return out
