"""Built-in synthetic data with known truth: an open bone-like surface scanned slice by slice.

The phantom is a curved tube of varying elliptical cross-section (a shaft widening into a
condyle-like end), seen from above by a linear probe swept along its axis: each frame sees the
upper part of one cross-section (the first echo of every vertical beam), steep flanks are missed,
the frame spacing varies, two runs of frames are missing (gaps) and segmentation drops short
stretches of some frames. The truth is the triangulated visible region. Everything is in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass
class Phantom:
    """Points ``(N, 3)`` mm, the visible truth surface (open mesh, mm) and per-point frame index."""

    points: np.ndarray
    truth: trimesh.Trimesh
    frame: np.ndarray


def _profile(y: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre offset in x, half-width a and half-height b (mm) of the cross-section at axial y."""
    t = y / length  # in [−0.5, 0.5]
    bump = np.exp(-(((t - 0.42) / 0.12) ** 2))          # condyle-like widening at one end
    a = 11.0 + 7.0 * bump + 1.0 * np.cos(6.0 * t)
    b = 8.0 + 3.0 * bump
    cx = 4.0 * np.sin(np.pi * t)                          # a gentle bend of the shaft
    return cx, a, b


def _surface(theta: np.ndarray, y: np.ndarray, length: float) -> np.ndarray:
    cx, a, b = _profile(y, length)
    return np.stack([cx + a * np.cos(theta), y, b * np.sin(theta)], axis=-1)


def _visible_limit(a: np.ndarray, b: np.ndarray, min_facing: float) -> np.ndarray:
    """Smallest θ at which the ellipse normal ∝ (b cos θ, a sin θ) still makes ``n_z ≥ min_facing``."""
    return np.arctan(min_facing * b / (a * np.sqrt(1.0 - min_facing**2)))


def bone_phantom(length: float = 120.0, frame_spacing: float = 0.8, beam_pitch: float = 0.2,
                 noise_mm: float = 0.15, jitter_mm: float = 0.2, min_facing: float = 0.35,
                 seed: int = 0) -> Phantom:
    """Simulate a sweep over the phantom and return its point cloud and visible truth.

    ``frame_spacing`` (mm) is the mean distance between frames (varying ×0.5–1.5), ``beam_pitch``
    (mm) the spacing of the vertical beams, ``noise_mm`` the in-plane segmentation noise (σ),
    ``jitter_mm`` the per-frame tracking error (σ of a rigid in-plane shift), ``min_facing`` the
    smallest vertical component of the surface normal that still returns an echo (steeper flanks
    are not seen, as in ultrasound).
    """
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0.5, 1.5, int(2 * length / frame_spacing)) * frame_spacing
    ys = -length / 2 + np.cumsum(steps)
    ys = ys[ys < length / 2]
    n = len(ys)
    keep = np.ones(n, dtype=bool)
    for centre in (0.3, 0.7):                      # two missing runs of frames (~4 mm gaps)
        i = int(centre * n)
        keep[i:i + int(4.0 / frame_spacing)] = False
    pts, frames = [], []
    for f in np.flatnonzero(keep):
        cx, a, b = (v[0] for v in _profile(np.array([ys[f]]), length))
        x = np.arange(cx - a, cx + a, beam_pitch)
        theta = np.arccos(np.clip((x - cx) / a, -1.0, 1.0))   # first echo of each vertical beam
        lim = _visible_limit(a, b, min_facing)
        seen = (theta > lim) & (theta < np.pi - lim)
        if rng.random() < 0.25:                    # a segmentation gap in this frame
            start = rng.uniform(0.0, 0.8) * len(x)
            column = np.arange(len(x))
            seen &= ~((column > start) & (column < start + 0.2 * len(x)))
        p = _surface(theta[seen], np.full(int(seen.sum()), ys[f]), length)
        p[:, [0, 2]] += rng.normal(0.0, noise_mm, (len(p), 2)) + rng.normal(0.0, jitter_mm, 2)
        pts.append(p)
        frames.append(np.full(len(p), f))
    truth = _truth_mesh(ys[keep].min(), ys[keep].max(), min_facing, length)
    return Phantom(points=np.concatenate(pts), truth=truth, frame=np.concatenate(frames))


def _truth_mesh(y0: float, y1: float, min_facing: float, length: float,
                n_theta: int = 120, n_y: int = 600) -> trimesh.Trimesh:
    """The visible region (per slice, θ between the two visibility limits) as a triangulated grid."""
    s = np.linspace(0.0, 1.0, n_theta)
    y = np.linspace(y0, y1, n_y)
    ss, yy = np.meshgrid(s, y, indexing="ij")
    _, a, b = _profile(yy, length)
    lim = _visible_limit(a, b, min_facing)
    theta = lim + ss * (np.pi - 2.0 * lim)
    vertices = _surface(theta.ravel(), yy.ravel(), length)
    idx = np.arange(n_theta * n_y).reshape(n_theta, n_y)
    a0, b0 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c0, d0 = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a0, b0, c0], 1), np.stack([a0, c0, d0], 1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def facing_surface(mesh: trimesh.Trimesh, direction=(0.0, 0.0, 1.0)) -> trimesh.Trimesh:
    """The open part of a closed mesh whose face normals have a positive component along
    ``direction`` — an ultrasound-like view from that side (used for the open-femur benchmark)."""
    d = np.asarray(direction, dtype=np.float64)
    keep = mesh.face_normals @ (d / np.linalg.norm(d)) > 0
    part = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    part.remove_unreferenced_vertices()
    return part
