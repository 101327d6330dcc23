"""Outlier removal for compounded bone points (SciPy KD-tree, CPU).

Statistical outlier removal: for each point the mean distance (mm) to its ``k`` nearest other
points; a point is an outlier when that mean exceeds both ``mean + std_ratio · std`` of all
points' means and ``floor_ratio`` × their median. It removes isolated false detections; it cannot remove a false structure seen coherently in
many frames (a fascia line), which is the segmenter's job.
"""

from __future__ import annotations

import numpy as np

from ..geometry.neighbors import kd_tree


def knn_mean_distance(points: np.ndarray, k: int) -> np.ndarray:
    """``(N,)`` mean distance (mm) from each point to its ``k`` nearest *other* points."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    if n < 2:
        return np.zeros(n)
    k = int(min(max(1, k), n - 1))
    dist, _ = kd_tree(pts).query(pts, k=k + 1, workers=1)
    return dist[:, 1:].mean(axis=1)


def statistical_outlier_mask(points: np.ndarray, k: int = 16, std_ratio: float = 2.0,
                             floor_ratio: float = 2.0) -> np.ndarray:
    """``(N,)`` bool, True for the points to keep (statistical outlier removal, see module doc).

    Args:
        points: ``(N, 3)`` coordinates, mm.
        k: neighbours per point.
        std_ratio: threshold in standard deviations above the mean of the per-point means.
        floor_ratio: never remove a point whose mean distance is below ``floor_ratio`` × the
            median one (on very regular clouds the standard deviation is tiny and the rule alone
            would strip the cloud's border).
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= k + 1:
        return np.ones(len(pts), dtype=bool)
    d = knn_mean_distance(pts, k)
    return d <= max(d.mean() + std_ratio * d.std(), floor_ratio * float(np.median(d)))


def radius_outlier_mask(points: np.ndarray, radius_mm: float, min_neighbors: int) -> np.ndarray:
    """``(N,)`` bool, True for points with at least ``min_neighbors`` other points within
    ``radius_mm``."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    tree = kd_tree(pts)
    counts = tree.query_ball_point(pts, r=radius_mm, return_length=True, workers=1)
    return (np.asarray(counts) - 1) >= min_neighbors
