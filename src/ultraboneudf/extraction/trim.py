"""Support trim: drop the faces of a mesh that lie away from the points it was built from.

A neural UDF can keep zero sets where no data constrains it: the tangent loss (§1.6) is satisfied
by a sheet continued in its own tangent plane past the rim of an open surface, and remnants of the
initial sphere survive where neither anchors nor grid queries reach (on the open femur, a bulb of
~50 mm beyond one epiphysis: 5% of the mesh area more than 40 mm from the truth). Such faces are far
from every input point, so a distance test removes them without touching the surface the data
supports. CAP-UDF's ``far`` trimming (§3.5 step 6) is the same rule.

The grazing trim (:func:`grazing_faces`) asks the beams instead: a bone face that the beams meet
nearly side-on sends no echo back to the probe, so a face lying along the beams of the echoes
around it is not a surface they imaged; it continues a streak of echoes along the beam (the band
of a segmentation running on past a steep side of the bone, the edge of a shadow).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..geometry.neighbors import kd_tree
from ..geometry.data_surface import DataSurface
from ..geometry.vectors import unit_rows


def unsupported_faces(mesh: trimesh.Trimesh, support: np.ndarray | DataSurface, max_distance: float,
                      max_normal: float = 0.0, max_rim: float = 0.0) -> np.ndarray:
    """(F,) bool: the faces of ``mesh`` whose mean vertex distance to ``support`` is ≥
    ``max_distance`` (same units as the mesh; ≤ 0: no limit) — the support-trim rule. ``support``:
    points (N, 3) (distance to the nearest one) or a
    :class:`~ultraboneudf.geometry.data_surface.DataSurface` (distance to the surface bridged across the
    data's gaps); with a ``DataSurface``, also the faces whose mean vertex distance along the
    surface's normal is ≥ ``max_normal`` (> 0), and those whose mean vertex distance past its rim
    within a sweep's image planes is ≥ ``max_rim`` (> 0)."""
    normal = rim = None
    if isinstance(support, DataSurface):
        dist, normal, rim = support.distances(mesh.vertices)
    else:
        dist, _ = kd_tree(support).query(mesh.vertices, k=1, workers=-1)
    out = np.zeros(len(mesh.faces), dtype=bool)
    if max_distance > 0:
        out |= dist[mesh.faces].mean(axis=1) >= max_distance
    if normal is not None and max_normal > 0:
        out |= normal[mesh.faces].mean(axis=1) >= max_normal
    if rim is not None and max_rim > 0:
        out |= rim[mesh.faces].mean(axis=1) >= max_rim
    return out


_GRAZING_NEIGHBOURS = 16  # the beams averaged around a face: up to this many nearest points


def grazing_faces(mesh: trimesh.Trimesh, points: np.ndarray, beams: np.ndarray, radius: float,
                  min_deg: float) -> np.ndarray:
    """(F,) bool: the faces of ``mesh`` that the beams of the ``points`` (N, 3) around them meet at
    ``min_deg`` or more from their normal. ``beams`` (N, 3): each point's beam direction (zero
    rows: unknown); a face's beam is the mean of those of its nearest points (up to 16) within
    ``radius`` (the mesh's unit) of its centre, and a face with none there is not judged."""
    told = np.any(beams != 0.0, axis=1)
    if min_deg <= 0 or not told.any() or len(mesh.faces) == 0:
        return np.zeros(len(mesh.faces), dtype=bool)
    centres = mesh.triangles_center
    unit = unit_rows(beams[told])
    k = min(_GRAZING_NEIGHBOURS, len(unit))
    dist, idx = kd_tree(points[told]).query(centres, k=k, distance_upper_bound=radius, workers=-1)
    dist, idx = dist.reshape(len(centres), k), idx.reshape(len(centres), k)
    within = np.isfinite(dist)
    mean = np.einsum("fk,fki->fi", within.astype(np.float64), unit[np.where(within, idx, 0)])
    length = np.linalg.norm(mean, axis=1)
    cos = np.abs(np.einsum("fi,fi->f", mean, mesh.face_normals)) / np.maximum(length, 1e-300)
    return (length > 0) & (cos <= np.cos(np.radians(min_deg)))  # no beam within the radius: length 0


def trim_to_support(mesh: trimesh.Trimesh | None, support: np.ndarray | DataSurface, max_distance: float,
                    max_normal: float = 0.0, max_rim: float = 0.0) -> trimesh.Trimesh | None:
    """``mesh`` without the faces of :func:`unsupported_faces` (mean vertex distance to ``support``
    ≥ ``max_distance``, or from a ``DataSurface`` along its normal ≥ ``max_normal`` or past its rim
    within a sweep's image planes ≥ ``max_rim``; same units as the mesh) and without the vertices
    no face uses any more. All limits ≤ 0 return ``mesh`` unchanged; ``None`` when no face is left."""
    if mesh is None or (max_distance <= 0 and max_normal <= 0 and max_rim <= 0):
        return mesh
    return without_faces(mesh, unsupported_faces(mesh, support, max_distance, max_normal, max_rim))


def without_faces(mesh: trimesh.Trimesh, drop: np.ndarray) -> trimesh.Trimesh | None:
    """``mesh`` without the faces ``drop`` (F,) bool marks and the vertices no face uses any more;
    ``mesh`` itself when none is marked, ``None`` when all are."""
    if not drop.any():
        return mesh
    if drop.all():
        return None
    out = trimesh.Trimesh(mesh.vertices, mesh.faces[~drop], process=False)
    out.remove_unreferenced_vertices()
    return out
