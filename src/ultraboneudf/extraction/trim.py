"""Support trim: drop the faces of a mesh that lie away from the points it was built from.

A neural UDF can keep zero sets where no data constrains it: the tangent loss (§1.6) is satisfied
by a sheet continued in its own tangent plane past the rim of an open surface, and remnants of the
initial sphere survive where neither anchors nor grid queries reach (on the open femur, a bulb of
~50 mm beyond one epiphysis: 5% of the mesh area more than 40 mm from the truth). Such faces are far
from every input point, so a distance test removes them without touching the surface the data
supports. CAP-UDF's ``far`` trimming (§3.5 step 6) is the same rule.
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..geometry.neighbors import kd_tree
from ..geometry.support import DataSurface


def unsupported_faces(mesh: trimesh.Trimesh, support: np.ndarray | DataSurface, max_distance: float
                      ) -> np.ndarray:
    """(F,) bool: the faces of ``mesh`` whose mean vertex distance to ``support`` is ≥
    ``max_distance`` (same units as the mesh) — the support-trim rule. ``support``: points (N, 3)
    (distance to the nearest one) or a :class:`~ultraboneudf.geometry.support.DataSurface`
    (distance to the surface bridged across the data's gaps)."""
    if isinstance(support, DataSurface):
        dist = support.distance(mesh.vertices)
    else:
        dist, _ = kd_tree(support).query(mesh.vertices, k=1, workers=-1)
    return dist[mesh.faces].mean(axis=1) >= max_distance


def trim_to_support(mesh: trimesh.Trimesh | None, support: np.ndarray | DataSurface, max_distance: float
                    ) -> trimesh.Trimesh | None:
    """``mesh`` without the faces whose mean vertex distance to ``support`` (points (N, 3) or a
    :class:`~ultraboneudf.geometry.support.DataSurface`) is ≥ ``max_distance`` (same units as the
    mesh), and without the vertices no face uses any more. ``max_distance ≤ 0`` returns ``mesh``
    unchanged; ``None`` when no face is left."""
    if mesh is None or max_distance <= 0:
        return mesh
    keep = ~unsupported_faces(mesh, support, max_distance)
    if keep.all():
        return mesh
    if not keep.any():
        return None
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    out.remove_unreferenced_vertices()
    return out
