"""The simulated probe's path: true image → world poses along the bone, the tracker's noisy record of
them, and the runs of frames a sweep loses. All lengths in mm, angles in degrees.

* **Path.** The sweep runs along the mesh's longest principal axis ``a``; the probe looks down
  ``−up`` (``up``: the smallest principal axis, or ``view``). Frame stations are spread over the
  bone's length minus ``margin_mm`` with a mean spacing ``frame_spacing_mm`` and a smoothly varying
  speed (``speed_variation``, relative). The probe face follows the skin: it stays
  ``tissue_depth_mm`` above the highest bone point in view, laterally centred on the bone (both
  smoothed as a hand would). The image plane is tilted about the lateral axis (``tilt_deg``) and
  rocked in-plane (``rock_deg``), slowly, plus hand jitter (``jitter_mm``, ``jitter_deg``, smooth
  over a few frames).
* **Tracking.** Recorded pose = true pose perturbed by a random rotation (``tracking_noise_deg``
  per axis, about the probe face centre) and translation (``tracking_noise_mm`` per axis).
* **Lost frames.** ``missing_runs`` runs of ``missing_run_mm`` of probe travel.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial.transform import Rotation

from ..errors import InputError
from .noise import smooth_noise
from .simulation_config import SimulationConfig
from .slicing import MeshArrays, slice_plane


def _principal_axes(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroid and principal axes (rows, longest first) of a surface."""
    c = mesh.triangles_center
    w = mesh.area_faces / max(mesh.area, 1e-12)
    mean = (c * w[:, None]).sum(axis=0)
    d = c - mean
    cov = (d * w[:, None]).T @ d
    vals, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].T
    for i in range(3):  # deterministic signs
        if axes[i][np.argmax(np.abs(axes[i]))] < 0:
            axes[i] = -axes[i]
    return mean, axes


def _unit(v: Any, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise InputError(f"{name} must be a non-zero 3-vector")
    return a / n


def _frame_rotation(lateral: np.ndarray, beam: np.ndarray, normal: np.ndarray) -> np.ndarray:
    return np.stack([lateral, beam, normal], axis=1)


# ------------------------------------------------------------------------------------------------
# probe path


def plan_path(mesh: trimesh.Trimesh, cfg: SimulationConfig, arrays: MeshArrays,
              rng: np.random.Generator) -> tuple[np.ndarray, dict[str, Any]]:
    """True image → world poses ``(F, 4, 4)`` of the sweep (image-plane mm → world mm)."""
    centre, axes = _principal_axes(mesh)
    a = axes[0] if cfg.sweep_axis is None else _unit(cfg.sweep_axis, "sweep_axis")
    up = axes[2] if cfg.view is None else _unit(cfg.view, "view")
    up = up - (up @ a) * a
    if np.linalg.norm(up) < 1e-6:
        raise InputError("view must not be parallel to the sweep axis")
    up /= np.linalg.norm(up)
    beam = -up
    lateral = np.cross(beam, a)
    w_mm = cfg.width_px * cfg.spacing_mm
    proj = (arrays.vertices - centre) @ a
    lo, hi = proj.min() + cfg.margin_mm, proj.max() - cfg.margin_mm
    if cfg.sweep_length_mm is not None:
        mid = 0.5 * (lo + hi)
        lo, hi = mid - cfg.sweep_length_mm / 2, mid + cfg.sweep_length_mm / 2
    length = hi - lo
    if length <= 0:
        raise InputError(f"the mesh is too short ({np.ptp(proj):.1f} mm) for a sweep with "
                         f"{cfg.margin_mm} mm margins")
    n = cfg.n_frames or int(round(length / cfg.frame_spacing_mm)) + 1
    n = max(2, int(n))
    speed = 1.0 + cfg.speed_variation * smooth_noise(rng, n, sigma=max(1.0, n / 10))[:, 0]
    speed = np.clip(speed, 0.2, None)
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])])
    s = lo + s / max(s[-1], 1e-12) * length
    spacing = length / max(n - 1, 1)

    # lateral centre and top of the bone in view at each station (nominal plane ⟂ a)
    centres = np.full(n, np.nan)
    tops = np.full(n, np.nan)
    for k in range(n):
        seg, _ = slice_plane(arrays, centre + a * s[k], a)
        if len(seg) == 0:
            continue
        p = seg.reshape(-1, 3) - centre
        x, h = p @ lateral, p @ up
        cx = 0.5 * (x.min() + x.max())
        sel = np.abs(x - cx) <= w_mm / 2
        centres[k] = cx
        tops[k] = h[sel].max() if sel.any() else h.max()
    ok = np.isfinite(centres)
    if not ok.any():
        raise InputError("the sweep planes miss the mesh entirely")
    idx = np.arange(n)
    centres = np.interp(idx, idx[ok], centres[ok])
    tops = np.interp(idx, idx[ok], tops[ok])
    win = max(1, int(round(5.0 / spacing)))
    sig = max(0.5, 5.0 / spacing)
    centres = ndimage.gaussian_filter1d(centres, sig, mode="nearest")
    tops = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(tops, 2 * win + 1), sig, mode="nearest")
    tops = np.maximum(tops, ndimage.maximum_filter1d(tops, 3))  # never dip into the bone

    slow = np.tanh(smooth_noise(rng, n, sigma=max(1.0, n / 8), dims=2))  # within ±1: amplitudes are maxima
    jit_sigma = 2.0
    jt = smooth_noise(rng, n, jit_sigma, dims=3) * cfg.jitter_mm
    jr = smooth_noise(rng, n, jit_sigma, dims=3) * cfg.jitter_deg
    base = _frame_rotation(lateral, beam, a)
    poses = np.empty((n, 4, 4))
    for k in range(n):
        local = Rotation.from_euler("xyz", [cfg.tilt_deg * slow[k, 0] + jr[k, 0], jr[k, 1],
                                            cfg.rock_deg * slow[k, 1] + jr[k, 2]], degrees=True)
        rot = base @ local.as_matrix()
        face = (centre + a * s[k] + lateral * centres[k] + up * (tops[k] + cfg.tissue_depth_mm)
                + jt[k] @ np.stack([lateral, up, a]))
        poses[k] = np.eye(4)
        poses[k, :3, :3] = rot
        poses[k, :3, 3] = face - rot[:, 0] * (w_mm / 2)
    return poses, {"sweep_axis": a.tolist(), "view": up.tolist(), "sweep_length_mm": float(length),
                   "mean_frame_spacing_mm": float(spacing)}


def perturb_poses(poses: np.ndarray, cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """Recorded poses: each true pose rotated about its probe face centre and shifted."""
    out = poses.copy()
    w_mm = cfg.width_px * cfg.spacing_mm
    for k in range(len(poses)):
        rot = poses[k, :3, :3]
        face = poses[k, :3, 3] + rot[:, 0] * (w_mm / 2)
        d_rot = Rotation.from_rotvec(np.deg2rad(cfg.tracking_noise_deg) * rng.standard_normal(3)).as_matrix()
        new_rot = d_rot @ rot
        new_face = face + cfg.tracking_noise_mm * rng.standard_normal(3)
        out[k, :3, :3] = new_rot
        out[k, :3, 3] = new_face - new_rot[:, 0] * (w_mm / 2)
    return out


def missing_frames(poses: np.ndarray, cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """``(F,)`` bool, True for the frames inside ``cfg.missing_runs`` runs of ``cfg.missing_run_mm``
    each, placed at random along the sweep (not overlapping, none at its ends)."""
    n = len(poses)
    out = np.zeros(n, dtype=bool)
    if cfg.missing_runs <= 0 or n < 3:
        return out
    face = poses[:, :3, 3] + poses[:, :3, 0] * (cfg.width_px * cfg.spacing_mm / 2)
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(face, axis=0), axis=1))])
    length, run = travel[-1], cfg.missing_run_mm
    # equal slots between 10% and 90% of the sweep, one run at a random place in each
    slots = np.linspace(0.1 * length, 0.9 * length, cfg.missing_runs + 1)
    for lo, hi in zip(slots[:-1], slots[1:]):
        start = rng.uniform(lo, max(lo, hi - run))
        out |= (travel >= start) & (travel < start + run)
    out[[0, -1]] = False
    return out
