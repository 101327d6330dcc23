"""The probe's beams: where each image column first meets the bone, and at what incidence. A beam
runs down each image column; its first crossing of the plane–mesh intersection is the surface it
sees, everything below lies in acoustic shadow. Lengths in mm, angles in degrees."""

from __future__ import annotations

import numpy as np

from .simulation_config import SimulationConfig
from .slicing import MeshArrays, first_hits, slice_plane


class ImageSlicer:
    """Slices the mesh by image planes, restricted to the faces near each image rectangle."""

    def __init__(self, arrays: MeshArrays, axis: np.ndarray, cfg: SimulationConfig) -> None:
        self.arrays = arrays
        self.axis = axis
        tri = arrays.vertices[arrays.faces]
        proj = tri @ axis
        self.fmin, self.fmax = proj.min(axis=1), proj.max(axis=1)
        self.order = np.argsort(self.fmin)
        self.sorted_min = self.fmin[self.order]
        self.max_span = float((self.fmax - self.fmin).max()) if len(proj) else 0.0
        self.w_mm = cfg.width_px * cfg.spacing_mm
        self.h_mm = cfg.height_px * cfg.spacing_mm

    def hits(self, pose: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(depth (W,) mm, face (W,) or -1)`` of the first hit of each beam at ``xs``."""
        rot, origin = pose[:3, :3], pose[:3, 3]
        corners = origin + np.array([[0, 0], [self.w_mm, 0], [0, self.h_mm],
                                     [self.w_mm, self.h_mm]]) @ rot[:, :2].T
        c = corners @ self.axis
        lo, hi = c.min() - 1e-6, c.max() + 1e-6
        start = np.searchsorted(self.sorted_min, lo - self.max_span, side="left")
        stop = np.searchsorted(self.sorted_min, hi, side="right")
        cand = self.order[start:stop]
        cand = cand[(self.fmax[cand] >= lo) & (self.fmin[cand] <= hi)]
        seg, fid = slice_plane(self.arrays, origin, rot[:, 2], face_subset=cand)
        if len(seg) == 0:
            return np.full(len(xs), np.inf), np.full(len(xs), -1)
        xy = (seg - origin) @ rot[:, :2]
        depth, which = first_hits(xy, xs, y_min=0.0)
        face = np.where(which >= 0, fid[np.maximum(which, 0)], -1)
        return depth, face


def incidence(arrays: MeshArrays, face: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """Incidence angle (degrees) of the beam on the hit faces; nan where no hit; > 90 for a back
    face (the probe inside the bone)."""
    out = np.full(len(face), np.nan)
    ok = face >= 0
    cos = -(arrays.normals[face[ok]] @ beam)
    out[ok] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out
