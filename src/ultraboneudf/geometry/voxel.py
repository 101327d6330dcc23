"""Voxel-mean down-sampling with a deterministic output order (§1.2 step 2)."""

from __future__ import annotations

import numpy as np


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean of the points in each occupied voxel of edge ``voxel`` (same unit as ``points``).

    Grid origin = bounding-box minimum − ``voxel / 2`` (Open3D's convention). Unlike Open3D, whose
    output order is a hash-map order, voxels are returned sorted lexicographically by their integer
    index, so the result is deterministic. ``voxel <= 0`` returns the points unchanged.
    Input ``(N, 3)``, output ``(M, 3)`` float64 with ``M ≤ N``.
    """
    points = np.asarray(points, dtype=np.float64)
    if voxel <= 0:
        return points.copy()
    origin = points.min(axis=0) - voxel / 2.0
    idx = np.floor((points - origin) / voxel).astype(np.int64)
    dims = idx.max(axis=0) + 1
    # Row-major packing keeps lexicographic order; fall back to a row-wise unique if it would overflow.
    if np.prod(dims.astype(np.float64)) < 2**62:
        keys = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts))
                     for k in range(3)], axis=1)
    return sums / counts[:, None]
