"""Training samples in unit space: surface subset, Gaussian and grid queries, anchors (§0.7, §0.8,
§1.2–1.4)."""

from __future__ import annotations

import numpy as np

from .fps import farthest_point_sampling
from .neighbors import kd_tree
from .neighbors import knn_distance


def surface_subset_index(points: np.ndarray, rule: str, threshold: int, fps_sizes: tuple[int, ...],
                         max_points: int, device: str = "cpu") -> np.ndarray | None:
    """Row indices into ``points`` of the surface rows ``P`` of :func:`surface_subset` (in ``P``'s
    order, duplicates kept), or ``None`` when ``P`` is every point in its own order. Lets per-point
    data (e.g. probe positions) follow the subset."""
    if rule == "all":
        return None
    if rule == "official":
        if len(points) <= threshold:
            return None
        # FPS from a fixed start is prefix-consistent: one run to the largest size serves all.
        order = farthest_point_sampling(points, max(fps_sizes), device=device)
        return np.concatenate([order[:size] for size in fps_sizes])
    if rule == "fps":
        if len(points) <= max_points:
            return None
        return farthest_point_sampling(points, max_points, device=device)
    raise ValueError(f"unknown surface subset rule {rule!r}")


def surface_subset(points: np.ndarray, rule: str, threshold: int, fps_sizes: tuple[int, ...],
                   max_points: int, device: str = "cpu") -> np.ndarray:
    """The surface rows ``P`` (unit space) used for training.

    ``official``: if ``len(points) > threshold``, FPS to each of ``fps_sizes`` (from index 0) and
    concatenate, keeping the duplicates (5k ∪ 15k → 20,000 rows, 15,000 distinct); else all points.
    ``fps``: FPS to ``max_points`` distinct points (all if fewer). ``all``: every point.
    """
    index = surface_subset_index(points, rule, threshold, fps_sizes, max_points, device)
    return points if index is None else points[index]


def gaussian_queries(surface: np.ndarray, sigma: np.ndarray, per_point: int,
                     rng: np.random.Generator) -> np.ndarray:
    """``per_point`` queries ``p + σ(p)·ε``, ε ~ N(0, I), stored consecutively per row:
    rows ``per_point·i … per_point·i + per_point − 1`` belong to point ``i``. Shape ``(N·per_point, 3)``."""
    eps = rng.standard_normal((len(surface), per_point, 3))
    return (surface[:, None, :] + sigma[:, None, None] * eps).reshape(-1, 3)


def grid_queries(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points drawn without replacement from the 70³ lattice on [−0.5, 0.5]³ and the 50³
    lattice on [−1, 1]³ (468,000 points, §0.8); ``(count, 3)``."""
    if count <= 0:
        return np.zeros((0, 3))
    fine = np.linspace(-0.5, 0.5, 70)
    coarse = np.linspace(-1.0, 1.0, 50)
    pool = np.concatenate([np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
                           for a in (fine, coarse)])
    return pool[rng.permutation(len(pool))[:count]]


def anchors(surface: np.ndarray, kind: str, resolution: int, squared: bool,
            min_target: float) -> tuple[np.ndarray, np.ndarray]:
    """Global-shape anchors ``(G, 3)`` and their targets ``(G,)`` (§1.4).

    ``official``: lattice ``linspace(−1, 1, resolution)³``; ``bbox``: lattice over the bounding box of
    ``surface``. Target = distance to the nearest surface row, squared if ``squared``; anchors whose
    target is not ``> min_target`` are dropped.
    """
    if kind == "official":
        axes = [np.linspace(-1.0, 1.0, resolution)] * 3
    elif kind == "bbox":
        lo, hi = surface.min(axis=0), surface.max(axis=0)
        axes = [np.linspace(lo[k], hi[k], resolution) for k in range(3)]
    else:
        raise ValueError(f"unknown anchor kind {kind!r}")
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, _ = kd_tree(surface).query(grid, k=1, workers=-1)
    target = dist**2 if squared else dist
    keep = target > min_target
    return grid[keep], target[keep]


def query_spread(surface: np.ndarray, k: int) -> np.ndarray:
    """σ(p) of §0.7: distance to the k-th nearest other row (duplicates at distance 0)."""
    return knn_distance(surface, k)
