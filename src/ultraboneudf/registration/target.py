"""The ultrasound side of a registration: the target's points thinned to an even spacing, with a
local plane (normal and flatness) at each, for the search's anchors and the refinement."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.neighbors import kd_tree
from ..geometry.voxel import voxel_downsample


@dataclass
class TargetCloud:
    """Target points in mm (the ultrasound's frame), thinned to one per ``voxel`` mm cell.

    ``points`` ``(N, 3)``; ``normals`` ``(N, 3)``: unit normals of the least-squares plane through
    the neighbours within ``radius`` mm (sign arbitrary); ``flatness`` ``(N,)``: the smallest
    eigenvalue of that neighbourhood's covariance over the sum of the three (0 on a plane, 1/3 for
    an isotropic blob); ``neighbours`` ``(N,)``: points within ``radius``.
    """

    points: np.ndarray
    normals: np.ndarray
    flatness: np.ndarray
    neighbours: np.ndarray
    voxel: float
    radius: float


def prepare_target(points: np.ndarray, voxel: float, radius: float, chunk: int = 4096, workers: int = -1
                   ) -> TargetCloud:
    """Thin ``points`` ``(N, 3)`` (mm) to ``voxel`` and fit a plane at every kept point through
    its neighbours within ``radius`` mm (points with fewer than 5 get flatness 1: never anchors);
    ``workers``: KD-tree threads (-1: all cores)."""
    x = voxel_downsample(np.asarray(points, dtype=np.float64), voxel)
    tree = kd_tree(x)
    normals = np.zeros_like(x)
    normals[:, 2] = 1.0
    flatness = np.ones(len(x))
    count = np.zeros(len(x), dtype=np.int64)
    k = int(min(len(x), max(8, round(4.0 * (radius / voxel) ** 2))))  # a disc of radius/voxel points, ×1.3
    for s in range(0, len(x), chunk):
        dist, idx = tree.query(x[s:s + chunk], k=k, distance_upper_bound=radius, workers=workers)
        valid = np.isfinite(dist)
        w = valid[..., None].astype(np.float64)
        nb = x[np.minimum(idx, len(x) - 1)]
        n = w.sum(axis=1)
        mean = (nb * w).sum(axis=1) / np.maximum(n, 1.0)
        centred = (nb - mean[:, None]) * w
        vals, vecs = np.linalg.eigh(np.einsum("cki,ckj->cij", centred, centred))
        ok = n[:, 0] >= 5
        normals[s:s + chunk][ok] = vecs[ok, :, 0]
        flatness[s:s + chunk][ok] = vals[ok, 0] / np.maximum(vals[ok].sum(axis=1), 1e-12)
        count[s:s + chunk] = n[:, 0].astype(np.int64)
    return TargetCloud(points=x, normals=normals, flatness=flatness, neighbours=count, voxel=float(voxel),
                       radius=float(radius))
