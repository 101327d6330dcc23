"""How well a mesh fits the points it was built from: a self-check without ground truth (the
sidecar's ``data_fit``, a warning from the command line)."""

from __future__ import annotations

import numpy as np
import trimesh

from ..extraction.trim import unsupported_faces
from ..geometry.neighbors import kd_tree

_FIT_MAX_POINTS = 200_000  # input points checked for coverage (every k-th row beyond this)
_FIT_MAX_SAMPLES = 2_000_000  # area samples standing in for the mesh


def data_fit(mesh: trimesh.Trimesh | None, points: np.ndarray, threshold_mm: float) -> dict:
    """How well a mesh fits the points it was built from, without any ground truth (a self-check).

    ``mesh`` and ``points`` (N, 3) in mm, same frame; ``threshold_mm`` > 0. Keys:
        ``threshold_mm``: the distance used below.
        ``input_far_fraction``: fraction of the points farther than the threshold from the mesh —
            data the surface does not reach (the field did not fit there, or a trim removed it).
        ``input_p95_mm``: 95th percentile of the point → mesh distance.
        ``mesh_far_area_fraction``: fraction of the mesh area in faces whose mean vertex distance to
            the nearest point is ≥ the threshold (the support-trim rule) — surface the data does not
            support.

    Point → mesh distances are to area samples spaced about threshold/10 apart (at most 2,000,000),
    so they overestimate by at most about that spacing; the samples are seeded (deterministic). At
    most 200,000 points are checked (every k-th row). ``None`` or a mesh without area covers nothing.
    """
    pts = np.asarray(points, dtype=np.float64)
    if mesh is None or len(mesh.faces) == 0 or not mesh.area > 0:
        return {"threshold_mm": float(threshold_mm), "input_far_fraction": 1.0,
                "input_p95_mm": float("inf"), "mesh_far_area_fraction": 0.0}
    area = float(mesh.area)
    spacing = threshold_mm / 10.0
    count = int(min(_FIT_MAX_SAMPLES, max(10_000, np.ceil(area / spacing**2))))
    samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    checked = pts[:: max(1, int(np.ceil(len(pts) / _FIT_MAX_POINTS)))]
    to_mesh, _ = kd_tree(samples).query(checked, k=1, workers=-1)
    far_faces = unsupported_faces(mesh, pts, threshold_mm)
    return {"threshold_mm": float(threshold_mm),
            "input_far_fraction": float((to_mesh > threshold_mm).mean()),
            "input_p95_mm": float(np.percentile(to_mesh, 95)),
            "mesh_far_area_fraction": float(mesh.area_faces[far_faces].sum() / area)}
