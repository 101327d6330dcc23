"""Outlier removal for compounded bone points (SciPy KD-tree, CPU).

Two rules, both over each point's ``k`` nearest other points (mm):

* ``local`` (the default): the local outlier factor (Breunig et al., 2000), how much sparser a
  point's neighbourhood is than its neighbours' own. A false echo beside the dense bone surface is
  much sparser than the surface points around it and is removed; the few echoes a steep face
  returns (weak oblique echoes drop out of the segmentation) are sparse together, each about as
  sparse as its neighbours, and are kept.
* ``statistical``: a point is an outlier when its mean distance to its neighbours exceeds both
  ``mean + std_ratio · std`` of all points' means and ``floor_ratio`` × their median. One threshold
  for the whole cloud, so it also removes every sparse but real part of the surface.

Neither removes a false structure seen coherently in many frames (a fascia line), which is the
segmenter's job.
"""

from __future__ import annotations

import numpy as np

from ..geometry.neighbors import kd_tree


def _nearest_others(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices ``(N, k')`` of each point's ``k' = min(k, N − 1)`` nearest *other*
    points (``N ≥ 2``)."""
    pts = np.asarray(points, dtype=np.float64)
    k = int(min(max(1, k), len(pts) - 1))
    dist, idx = kd_tree(pts).query(pts, k=k + 1, workers=1)
    return dist[:, 1:], idx[:, 1:]


def knn_mean_distance(points: np.ndarray, k: int) -> np.ndarray:
    """``(N,)`` mean distance (mm) from each point to its ``k`` nearest *other* points."""
    if len(points) < 2:
        return np.zeros(len(points))
    return _nearest_others(points, k)[0].mean(axis=1)


def statistical_outlier_mask(points: np.ndarray, k: int = 16, std_ratio: float = 2.0,
                             floor_ratio: float = 2.0) -> np.ndarray:
    """``(N,)`` bool, True for the points to keep (the ``statistical`` rule of the module doc).

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


def local_outlier_factor(points: np.ndarray, k: int = 16) -> np.ndarray:
    """``(N,)`` local outlier factor of each point over its ``k`` nearest other points: the mean
    local reachability density of the neighbours over the point's own (about 1 inside a surface
    of any density, large for a point isolated beside a denser one). Duplicated points count as
    neighbours at distance 0."""
    if len(points) < 2:
        return np.ones(len(points))
    dist, idx = _nearest_others(points, k)
    # reachability distance of p from its neighbour o: at least o's own k-distance, so that the
    # points of one dense cluster do not tell apart by their exact spacing
    reach = np.maximum(dist, dist[:, -1][idx])
    density = 1.0 / np.maximum(reach.mean(axis=1), 1e-12)
    return density[idx].mean(axis=1) / density


def local_outlier_mask(points: np.ndarray, k: int = 16, factor: float = 1.5) -> np.ndarray:
    """``(N,)`` bool, True for the points to keep: local outlier factor (:func:`local_outlier_factor`,
    ``k`` neighbours) below ``factor``."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= k + 1:
        return np.ones(len(pts), dtype=bool)
    return local_outlier_factor(pts, k) < factor


OUTLIER_RULES = ("local", "statistical")
"""Rules of :func:`outlier_mask` (see the module docstring)."""


def outlier_mask(points: np.ndarray, rule: str = "local", k: int = 16, std_ratio: float = 2.0,
                 factor: float = 1.5) -> np.ndarray:
    """``(N,)`` bool, True for the points to keep under ``rule``: ``local`` (:func:`local_outlier_mask`
    with ``k`` and ``factor``) or ``statistical`` (:func:`statistical_outlier_mask` with ``k`` and
    ``std_ratio``)."""
    if rule == "local":
        return local_outlier_mask(points, k, factor)
    if rule == "statistical":
        return statistical_outlier_mask(points, k, std_ratio)
    raise ValueError(f"unknown outlier rule {rule!r}; choose one of {', '.join(OUTLIER_RULES)}")


def radius_outlier_mask(points: np.ndarray, radius_mm: float, min_neighbors: int) -> np.ndarray:
    """``(N,)`` bool, True for points with at least ``min_neighbors`` other points within
    ``radius_mm``."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    tree = kd_tree(pts)
    counts = tree.query_ball_point(pts, r=radius_mm, return_length=True, workers=1)
    return (np.asarray(counts) - 1) >= min_neighbors
