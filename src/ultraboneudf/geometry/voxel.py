"""Voxel-mean down-sampling with a deterministic output order (§1.2 step 2)."""

from __future__ import annotations

import numpy as np


def voxel_groups(points: np.ndarray, voxel: float, origin: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Voxel id ``(N,)`` of every point (ids numbered in lexicographic voxel-index order) and the
    number of points ``(M,)`` of each occupied voxel. The grid's corner is ``origin`` (3,), at or
    below every point; by default the bounding-box minimum − ``voxel / 2``."""
    if origin is None:
        origin = points.min(axis=0) - voxel / 2.0
    idx = np.floor((points - origin) / voxel).astype(np.int64)
    dims = idx.max(axis=0) + 1
    # Row-major packing keeps lexicographic order; fall back to a row-wise unique if it would overflow.
    if np.prod(dims.astype(np.float64)) < 2**62:
        keys = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    return inverse.reshape(-1), counts


def group_mean(values: np.ndarray, inverse: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per-voxel mean ``(M, K)`` of the rows of ``values`` ``(N, K)``."""
    sums = np.stack([np.bincount(inverse, weights=values[:, k], minlength=len(counts))
                     for k in range(values.shape[1])], axis=1)
    return sums / counts[:, None]


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
    inverse, counts = voxel_groups(points, voxel)
    return group_mean(points, inverse, counts)


def voxel_downsample_with(points: np.ndarray, attributes: np.ndarray, voxel: float
                          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`voxel_downsample` that carries per-point ``attributes`` ``(N, K)`` along: each output
    row gets the mean attribute of the points averaged into it (e.g. the probe position of a sweep
    point → the mean probe position of the points in its voxel). Returns ``(M, 3)`` points, rows
    identical to :func:`voxel_downsample`, and ``(M, K)`` float64 attributes."""
    points = np.asarray(points, dtype=np.float64)
    attributes = np.asarray(attributes, dtype=np.float64)
    if attributes.ndim != 2 or len(attributes) != len(points):
        raise ValueError(f"attributes must be (N, K) with N = {len(points)} rows, got {attributes.shape}")
    if voxel <= 0:
        return points.copy(), attributes.copy()
    inverse, counts = voxel_groups(points, voxel)
    return group_mean(points, inverse, counts), group_mean(attributes, inverse, counts)
