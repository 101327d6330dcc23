"""Plane–mesh slicing and first hits along parallel beams (vectorised NumPy, no ray tracer).

The image plane of a linear probe cuts a closed mesh in a set of segments. A beam is a line down
one image column, so the first surface it meets is the shallowest segment crossing that column:
one 2-D interval test per (column, segment) instead of a 3-D ray cast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass
class MeshArrays:
    """Flat arrays of a triangle mesh for fast repeated slicing (mm)."""

    vertices: np.ndarray   # (V, 3)
    faces: np.ndarray      # (M, 3) int
    normals: np.ndarray    # (M, 3) outward unit face normals

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh) -> "MeshArrays":
        return cls(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64),
                   np.asarray(mesh.face_normals, dtype=np.float64))


def slice_plane(mesh: MeshArrays, origin: np.ndarray, normal: np.ndarray,
                face_subset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of a mesh with the plane through ``origin`` with unit ``normal``.

    Returns ``(segments (S, 2, 3) mm, face index (S,))``. Vertices lying exactly on the plane are
    nudged by 1e-9 mm so every crossing face yields exactly one segment.
    """
    d = (mesh.vertices - origin) @ normal
    d = np.where(d == 0.0, 1e-9, d)
    faces = mesh.faces if face_subset is None else mesh.faces[face_subset]
    fd = d[faces]
    pos = fd > 0
    n_pos = pos.sum(axis=1)
    crossing = (n_pos == 1) | (n_pos == 2)
    idx = np.flatnonzero(crossing)
    if len(idx) == 0:
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=np.int64)
    f = faces[idx]
    fdc = fd[idx]
    # the lone vertex (the one on its own side of the plane) and its two partners
    lone_is_pos = n_pos[idx] == 1
    lone_mask = np.where(lone_is_pos[:, None], pos[idx], ~pos[idx])
    lone = np.argmax(lone_mask, axis=1)
    a_i = (lone + 1) % 3
    b_i = (lone + 2) % 3
    rows = np.arange(len(idx))
    v = mesh.vertices
    p0 = v[f[rows, lone]]
    pa = v[f[rows, a_i]]
    pb = v[f[rows, b_i]]
    d0, da, db = fdc[rows, lone], fdc[rows, a_i], fdc[rows, b_i]
    ta = (d0 / (d0 - da))[:, None]
    tb = (d0 / (d0 - db))[:, None]
    seg = np.stack([p0 + ta * (pa - p0), p0 + tb * (pb - p0)], axis=1)
    fid = idx if face_subset is None else np.asarray(face_subset)[idx]
    return seg, fid


def first_hits(seg_xy: np.ndarray, xs: np.ndarray, y_min: float = 0.0,
               chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Shallowest crossing per beam.

    Args:
        seg_xy: ``(S, 2, 2)`` segments in image-plane mm (x lateral, y depth).
        xs: ``(W,)`` lateral positions of the beams, mm.
        y_min: ignore crossings shallower than this (above the probe face).

    Returns:
        ``(depth (W,), segment index (W,))``: depth in mm (inf where no crossing) and the index of
        the crossing segment (-1 where none).
    """
    w = len(xs)
    best = np.full(w, np.inf)
    which = np.full(w, -1, dtype=np.int64)
    if len(seg_xy) == 0:
        return best, which
    x0, y0 = seg_xy[:, 0, 0], seg_xy[:, 0, 1]
    x1, y1 = seg_xy[:, 1, 0], seg_xy[:, 1, 1]
    lo, hi = np.minimum(x0, x1), np.maximum(x0, x1)
    dx = x1 - x0
    for s in range(0, len(seg_xy), chunk):
        sl = slice(s, s + chunk)
        inside = (xs[:, None] >= lo[None, sl]) & (xs[:, None] < hi[None, sl])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (xs[:, None] - x0[None, sl]) / dx[None, sl]
        y = y0[None, sl] + t * (y1 - y0)[None, sl]
        y = np.where(inside & (y >= y_min), y, np.inf)
        j = np.argmin(y, axis=1)
        yj = y[np.arange(w), j]
        better = yj < best
        best[better] = yj[better]
        which[better] = j[better] + s
    return best, which
