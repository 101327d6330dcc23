"""Analytic test geometry for registration: a bone-like body with no symmetry, a one-sided noisy
view of it with clustered false echoes, and known rigid motions."""

from __future__ import annotations

import numpy as np
import trimesh

from ultraboneudf.registration import rigid


def lumpy_bone() -> trimesh.Trimesh:
    """A closed, elongated body (about 45 × 45 × 120 mm) whose radius varies with direction by a
    mix of smooth terms and six bumps (2–4 mm high, about 8 mm wide) that no rotation or mirror maps
    onto itself."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    u = sphere.vertices
    radius = 1.0 + 0.22 * u[:, 0] + 0.15 * u[:, 1] * u[:, 2] + 0.18 * u[:, 2] ** 3 + 0.12 * u[:, 0] * u[:, 1]
    bumps = np.array([[0.9, 0.3, 0.3], [0.7, -0.6, -0.2], [0.8, 0.1, -0.6], [0.5, 0.5, 0.7],
                      [-0.6, 0.7, 0.2], [-0.3, -0.8, 0.5]])
    bumps /= np.linalg.norm(bumps, axis=1, keepdims=True)
    heights = np.array([0.15, 0.12, 0.18, 0.1, 0.15, 0.12])
    radius += (heights * np.exp(-np.sum((u[:, None] - bumps) ** 2, axis=2) / 0.05)).sum(axis=1)
    v = u * radius[:, None] * 22.0
    v[:, 2] *= 2.5
    return trimesh.Trimesh(v, sphere.faces, process=False)


def one_sided_view(mesh: trimesh.Trimesh, seed: int = 0, n: int = 4000, noise_mm: float = 0.3,
                   outlier_share: float = 0.3) -> np.ndarray:
    """Points on the part of ``mesh`` that faces +x and lies in the upper two thirds (about a
    quarter of the surface), Gaussian noise of ``noise_mm``, and false echoes making up
    ``outlier_share`` of all points (as on real clouds: 23–36%): half in five tight clusters 3–10 mm
    off the surface, half in a sheet 6 mm above it."""
    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, 6 * n, seed=seed)
    normals = mesh.face_normals[faces]
    z0 = mesh.bounds[0, 2] + (mesh.bounds[1, 2] - mesh.bounds[0, 2]) / 3.0
    keep = (normals[:, 0] > 0.35) & (points[:, 2] > z0)
    points, normals = points[keep][:n], normals[keep][:n]
    points = points + rng.normal(0.0, noise_mm, points.shape)
    k = int(round(outlier_share * len(points) / (1.0 - outlier_share)))
    centres = rng.choice(len(points), 5, replace=False)
    blobs = [points[c] + normals[c] * rng.uniform(3.0, 10.0) + rng.normal(0.0, 1.5, (k // 10, 3)) for c in centres]
    sheet_at = rng.choice(len(points), k - 5 * (k // 10), replace=False)
    sheet = points[sheet_at] + normals[sheet_at] * 6.0
    return np.concatenate([points, *blobs, sheet])


def motion(angle_deg: float, axis, shift, centre) -> np.ndarray:
    """A 4×4: a turn of ``angle_deg`` about ``axis`` through ``centre``, then ``shift`` (mm)."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    r = rigid.axis_angle(axis, np.radians(angle_deg))
    centre = np.asarray(centre, dtype=float)
    return rigid.homogeneous(r, centre - r @ centre + np.asarray(shift, dtype=float))


def mean_error(found: np.ndarray, truth: np.ndarray, mesh: trimesh.Trimesh) -> float:
    """Mean distance (mm) the vertices of ``mesh`` move between the two transforms."""
    return float(rigid.displacement(found, truth, np.asarray(mesh.vertices)).mean())
