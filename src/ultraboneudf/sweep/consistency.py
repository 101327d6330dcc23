"""Frame-to-frame consistency of detected bone surfaces.

A bone surface is continuous: where the probe moves a fraction of a millimetre between frames,
the echo found in one frame continues in its neighbours. Speckle, a wire or a flickering
reverberation found in one frame alone does not. :func:`consistent_detections` keeps a detected
surface point when some neighbouring frame that *can* see it (near enough, the point inside its
image) also has a detection near it; it does not judge frames whose neighbours are all far away
(a sparse subset of a sweep), and keeps their points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.neighbors import kd_tree
from .model import Sweep
from .transforms import pixels_to_world


@dataclass
class ConsistencyReport:
    """What :func:`consistent_detections` did: ``removed``/``judged``/``kept`` point counts and the
    number of frames that had at least one neighbour near enough to judge them."""

    removed: int
    judged: int
    kept: int
    frames_judged: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def consistent_detections(sweep: Sweep, rows: np.ndarray, neighbours: int = 2, reach_mm: float = 4.0,
                          tol_mm: float = 1.5, slope: float = 1.0) -> tuple[np.ndarray, ConsistencyReport]:
    """Drop detected surface points that do not continue into neighbouring frames.

    Args:
        sweep: the sweep (its geometry is used, in mm).
        rows: ``(F, W)`` surface row per frame and scan line (NaN where none), as
            :meth:`BoneDetector.detect` gives them.
        neighbours: frames on each side that may confirm a point.
        reach_mm: a neighbour judges a point only if the point lies within this distance of the
            neighbour's image plane (and inside its image).
        tol_mm: a point is confirmed when a detection of the neighbour lies within ``tol_mm +
            slope · d`` of it, ``d`` the point's distance to the neighbour's plane (a surface
            inclined to the image plane shifts between frames).
        slope: see ``tol_mm``.

    Returns:
        ``(rows, report)``: a copy of ``rows`` with the unconfirmed points set to NaN.
    """
    rows = np.asarray(rows, dtype=np.float64)
    n, w = rows.shape
    p2w = sweep.pixel_to_world()
    w2p = np.linalg.inv(p2w)
    cols = np.arange(w, dtype=np.float64)
    points, trees = [], []
    for i in range(n):
        ok = np.isfinite(rows[i])
        pts = pixels_to_world(p2w[i], cols[ok], rows[i][ok])
        points.append((np.flatnonzero(ok), pts))
        trees.append(kd_tree(pts) if len(pts) else None)
    normals = sweep.image_to_world[:, :3, 2]
    origins = sweep.image_to_world[:, :3, 3]
    out = rows.copy()
    removed = judged = frames_judged = 0
    for i in range(n):
        idx, pts = points[i]
        if len(pts) == 0:
            continue
        confirmed = np.zeros(len(pts), dtype=bool)
        can_judge = np.zeros(len(pts), dtype=bool)
        for j in range(max(0, i - neighbours), min(n, i + neighbours + 1)):
            if j == i:
                continue
            d = np.abs((pts - origins[j]) @ normals[j])
            pix = (w2p[j][:3, :3] @ pts.T).T + w2p[j][:3, 3]
            inside = ((d <= reach_mm) & (pix[:, 0] >= 0) & (pix[:, 0] <= sweep.width - 1)
                      & (pix[:, 1] >= 0) & (pix[:, 1] <= sweep.height - 1))
            if not inside.any():
                continue
            can_judge |= inside
            if trees[j] is None:
                continue
            dist, _ = trees[j].query(pts[inside], k=1)
            confirmed[np.flatnonzero(inside)] |= dist <= tol_mm + slope * d[inside]
        drop = can_judge & ~confirmed
        if can_judge.any():
            frames_judged += 1
        judged += int(can_judge.sum())
        removed += int(drop.sum())
        out[i, idx[drop]] = np.nan
    kept = int(np.isfinite(out).sum())
    return out, ConsistencyReport(removed, judged, kept, frames_judged)


__all__ = ["consistent_detections", "ConsistencyReport"]
