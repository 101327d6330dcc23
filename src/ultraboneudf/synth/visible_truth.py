"""The visible ground truth of a simulated sweep: the faces of the closed mesh the beams see.

Beams every ``gt_step_mm`` across the image and along the sweep (poses interpolated between
frames), or every sixth of the mesh's median edge where that is finer; faces first hit at an
incidence below ``max_incidence_deg`` by a beam inside the image are visible; single-face holes are
closed. This is the paper's OpenBoneCT truth: the part of the bone an ultrasound sweep can show.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from ..progress import QUIET, Progress
from .beams import ImageSlicer, incidence
from .simulation_config import SimulationConfig


def _interpolate_poses(poses: np.ndarray, step_mm: float, w_mm: float) -> np.ndarray:
    """Poses between consecutive frames every ``step_mm`` of probe-face travel (slerp + lerp)."""
    out = []
    for k in range(len(poses) - 1):
        p0, p1 = poses[k], poses[k + 1]
        c0 = p0[:3, 3] + p0[:3, 0] * w_mm / 2
        c1 = p1[:3, 3] + p1[:3, 0] * w_mm / 2
        m = max(1, int(np.ceil(np.linalg.norm(c1 - c0) / step_mm)))
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([p0[:3, :3], p1[:3, :3]])))
        ts = np.arange(m) / m
        rots = slerp(ts).as_matrix()
        for t, r in zip(ts, rots):
            c = c0 + t * (c1 - c0)
            q = np.eye(4)
            q[:3, :3] = r
            q[:3, 3] = c - r[:, 0] * w_mm / 2
            out.append(q)
    out.append(poses[-1])
    return np.stack(out)


def truth_beam_spacing(mesh: trimesh.Trimesh, cfg: SimulationConfig) -> float:
    """Spacing (mm) of the visible-truth pass's beams, across the image and along the sweep:
    ``cfg.gt_step_mm``, or a sixth of the mesh's median edge where that is smaller. A face counts as
    visible only if a beam hits it, so beams coarser than the faces leave most faces of a steep
    surface unhit (at 75° incidence the beams land 3.9 × their spacing apart on it) and the truth
    full of holes; a sixth of an edge resolves the faces up to the 75° cut."""
    edge = float(np.median(mesh.edges_unique_length)) if len(mesh.faces) else cfg.gt_step_mm
    return min(cfg.gt_step_mm, edge / 6.0)


def visible_surface(mesh: trimesh.Trimesh, hit_faces: np.ndarray) -> trimesh.Trimesh:
    """Sub-mesh of the hit faces, with faces having ≥ 2 hit neighbours added (closes pinholes)."""
    vis = np.zeros(len(mesh.faces), dtype=bool)
    vis[hit_faces] = True
    adj = mesh.face_adjacency
    count = np.zeros(len(mesh.faces), dtype=np.int64)
    np.add.at(count, adj[:, 0], vis[adj[:, 1]])
    np.add.at(count, adj[:, 1], vis[adj[:, 0]])
    vis |= count >= 2
    faces = np.flatnonzero(vis)
    if len(faces) == 0:
        return trimesh.Trimesh()
    sub = mesh.submesh([faces], append=True)
    sub.remove_unreferenced_vertices()
    return sub


def visible_truth(mesh: trimesh.Trimesh, poses: np.ndarray, slicer: ImageSlicer, cfg: SimulationConfig,
                  progress: Progress = QUIET) -> tuple[trimesh.Trimesh, float]:
    """The visible surface of ``mesh`` seen from the true ``poses`` ``(F, 4, 4)``, and the spacing
    (mm) of the beams that looked (:func:`truth_beam_spacing`)."""
    w, h = cfg.width_px, cfg.height_px
    beam_mm = truth_beam_spacing(mesh, cfg)
    dense = _interpolate_poses(poses, beam_mm, w * cfg.spacing_mm)
    beams = np.arange(0.5 * beam_mm, w * cfg.spacing_mm, beam_mm)
    hit: list[np.ndarray] = []
    with progress.stage("visible GT", len(dense)) as advance:
        for q in dense:
            depth, face = slicer.hits(q, beams)
            inc = incidence(slicer.arrays, face, q[:3, 1])
            ok = (depth < h * cfg.spacing_mm) & (np.nan_to_num(inc, nan=180.0) <= cfg.max_incidence_deg)
            hit.append(face[ok])
            advance(1)
    hit_faces = np.unique(np.concatenate(hit)) if hit else np.zeros(0, np.int64)
    return visible_surface(mesh, hit_faces), beam_mm
