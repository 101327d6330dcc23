"""Scores of a sweep's outputs against the simulator's truth: segmentation precision/recall,
point-to-surface distances and coverage of the visible surface. All lengths in mm."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import ndimage

from ..geometry.neighbors import kd_tree


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                                c: np.ndarray) -> np.ndarray:
    """Closest point to each ``p[i]`` on triangle ``(a[i], b[i], c[i])`` (all ``(N, 3)``), exact.

    Barycentric region tests (vertex, edge or face region), vectorised.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    out = np.empty_like(p)
    done = np.zeros(len(p), dtype=bool)

    def put(mask: np.ndarray, value: np.ndarray) -> None:
        m = mask & ~done
        out[m] = value[m]
        done[m] = True

    put((d1 <= 0) & (d2 <= 0), a)
    put((d3 >= 0) & (d4 <= d3), b)
    put((d6 >= 0) & (d5 <= d6), c)
    with np.errstate(divide="ignore", invalid="ignore"):
        v_ab = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + v_ab[:, None] * ab)
        w_ac = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + w_ac[:, None] * ac)
        w_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + w_bc[:, None] * (c - b))
        denom = va + vb + vc
        v = vb / denom
        w = vc / denom
        put(np.ones(len(p), dtype=bool), a + v[:, None] * ab + w[:, None] * ac)
    return out


def point_to_mesh_distance(points: np.ndarray, mesh: trimesh.Trimesh, candidates: int = 16,
                           max_edge_mm: float = 2.0, chunk: int = 100_000) -> np.ndarray:
    """``(N,)`` unsigned distance (mm) from each point to the mesh surface.

    Exact point–triangle distances over the ``candidates`` faces whose centroids are nearest
    (a KD-tree), after splitting faces to edges ≤ ``max_edge_mm`` (long faces have far-away
    centroids). For points within a few mm of the surface this is the exact distance; in general
    it is an upper bound.
    """
    pts = np.asarray(points, dtype=np.float64)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(faces) and mesh.edges_unique_length.max() > max_edge_mm:
        vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge_mm)
    tri = np.asarray(vertices, dtype=np.float64)[faces]
    tree = kd_tree(tri.mean(axis=1))
    k = int(min(candidates, len(tri)))
    out = np.empty(len(pts))
    for s in range(0, len(pts), chunk):
        p = pts[s:s + chunk]
        _, idx = tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        pr = np.repeat(p, k, axis=0)
        t = tri[idx.reshape(-1)]
        q = closest_points_on_triangles(pr, t[:, 0], t[:, 1], t[:, 2])
        out[s:s + chunk] = np.linalg.norm(pr - q, axis=1).reshape(len(p), k).min(axis=1)
    return out


def surface_coverage(surface: trimesh.Trimesh, points: np.ndarray, radius_mm: float = 1.0,
                     samples: int = 50_000, seed: int = 0) -> float:
    """Fraction of ``surface`` area within ``radius_mm`` of some point (area-uniform samples)."""
    if len(surface.faces) == 0 or len(points) == 0:
        return 0.0
    rng = np.random.default_rng(seed)
    tri = np.asarray(surface.triangles, dtype=np.float64)
    area = surface.area_faces
    face = rng.choice(len(tri), size=samples, p=area / area.sum())
    u, v = rng.random(samples), rng.random(samples)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[face]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    d, _ = kd_tree(np.asarray(points, dtype=np.float64)).query(pts, k=1, distance_upper_bound=radius_mm)
    return float(np.mean(np.isfinite(d)))


def mask_precision_recall(pred: np.ndarray, true: np.ndarray, spacing_mm: float,
                          tolerance_mm: float = 0.5) -> tuple[float, float]:
    """Pixel precision and recall of bone masks ``(F, H, W)`` with a distance tolerance.

    A predicted pixel is correct when a true pixel of the same frame lies within
    ``tolerance_mm``; a true pixel is found when a predicted pixel lies within it. Sums over all
    frames (micro-average). Empty sets give 1.0 (nothing wrong / nothing to find).
    """
    tol = tolerance_mm / spacing_mm
    tp_p = n_p = tp_r = n_r = 0
    for pk, tk in zip(np.asarray(pred, bool), np.asarray(true, bool)):
        if pk.any():
            dt = ndimage.distance_transform_edt(~tk) if tk.any() else np.full(tk.shape, np.inf)
            tp_p += int((dt[pk] <= tol).sum())
            n_p += int(pk.sum())
        if tk.any():
            dp = ndimage.distance_transform_edt(~pk) if pk.any() else np.full(pk.shape, np.inf)
            tp_r += int((dp[tk] <= tol).sum())
            n_r += int(tk.sum())
    return (tp_p / n_p if n_p else 1.0), (tp_r / n_r if n_r else 1.0)
