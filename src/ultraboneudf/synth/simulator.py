"""Tracked freehand sweep simulator with known truth.

Given a closed bone mesh (mm), :func:`simulate_sweep` moves a linear probe along the bone and
produces, per frame: the B-mode-like image, the true bone mask, a "predicted" mask with the errors
of a real segmentation network, and the probe pose with tracking noise. It also returns the
visible ground-truth surface (the mesh faces seen by at least one beam, the paper's OpenBoneCT
truth) next to the closed mesh. :meth:`SimulatedSweep.write` stores it all in the UltraBones100k
sample layout, so every reader and the whole pipeline run on it unchanged.

Model (all lengths in mm):

* **Probe path.** The sweep runs along the mesh's longest principal axis ``a``; the probe looks
  down ``−up`` (``up``: the smallest principal axis, or ``view``). Frame stations are spread over
  the bone's length minus ``margin_mm`` with a mean spacing ``frame_spacing_mm`` and a smoothly
  varying speed (``speed_variation``, relative). The probe face follows the skin: it stays
  ``tissue_depth_mm`` above the highest bone point in view, laterally centred on the bone
  (both smoothed as a hand would). The image plane is tilted about the lateral axis (``tilt_deg``)
  and rocked in-plane (``rock_deg``), slowly, plus hand jitter (``jitter_mm``, ``jitter_deg``,
  smooth over a few frames). Frames come at ``frame_rate_hz``.
* **Beams.** A beam runs down each image column. Its first crossing of the plane–mesh
  intersection is the surface it sees; everything below is in acoustic shadow. A surface hit at an
  incidence angle (beam vs surface normal) above ``max_incidence_deg`` returns no echo and is not
  part of the visible truth.
* **Image.** Rayleigh speckle (correlated over ``speckle_axial_mm`` × ``speckle_lateral_mm``) on a
  soft-tissue background with a skin line and ``n_fascia`` bright fascia lines (bright echoes
  without shadow: the detector's hard negatives), depth attenuation, the bone echo (brightness
  ∝ cos(incidence)^1.5, a thin band with a short tail) and the shadow below it (``shadow_level``
  of the tissue brightness), log-compressed to 8 bits.
* **Predicted mask.** The true surface row per column with a per-frame bias and smooth boundary
  jitter (``pred_jitter_px``), ``pred_thickness_px`` thick; gaps (``pred_gap_fraction`` of the
  columns in runs of mean ``pred_gap_mean_mm``), weak echoes dropped above
  ``pred_max_incidence_deg``, and ``pred_fp_per_frame`` off-surface false positives (short
  segments on fascia or just below the bone, like reverberations); for the ``real`` level also an
  offset along the beam drifting along the sweep and false echoes that persist over neighbouring
  frames, from their own random stream (:func:`add_clutter`: fascia sheets in front of the bone,
  streaks rising from it, reverberation clusters under it).
* **Tracking.** Recorded pose = true pose perturbed by a random rotation (``tracking_noise_deg``
  per axis, about the probe face centre) and translation (``tracking_noise_mm`` per axis).
* **Visible truth.** Beams every ``gt_step_mm`` across the image and along the sweep (poses
  interpolated between frames), or every sixth of the mesh's median edge where that is finer; faces
  first hit at an incidence below ``max_incidence_deg`` by a beam inside the image are visible;
  single-face holes are closed.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial.transform import Rotation, Slerp

from .._version import __version__
from ..errors import InputError
from ..io import atomic_write_bytes, save_json
from ..progress import QUIET, Progress
from ..sweep.model import Sweep
from ..sweep.formats import ultrabones
from ..sweep.transforms import pixels_to_world, rigid_from_euler
from .slicing import MeshArrays, first_hits, slice_plane
from .simulation_config import NOISE_PRESETS, SimulationConfig, config_with_noise

DEFAULT_CALIBRATION = rigid_from_euler([26.0, -0.5, 128.0], [92.5, -0.5, 179.2])
"""A probe calibration like the UltraBones100k sample's (image-plane mm → probe frame)."""


@dataclass
class SimulatedSweep:
    """Output of :func:`simulate_sweep`.

    Attributes:
        sweep: the recorded sweep: images ``(F, H, W)`` uint8, predicted masks, poses *with*
            tracking noise, pixel offset 0.5 (UltraBones100k convention).
        true_image_to_world: ``(F, 4, 4)`` exact poses.
        true_masks: ``(F, H, W)`` bool, the visible bone surface pixel of each scan line.
        pred_masks: ``(F, H, W)`` bool, the "predicted" masks (same as ``sweep.masks``).
        surface_depth_mm: ``(F, W)`` first-hit depth along each beam (inf: no bone), mm.
        incidence_deg: ``(F, W)`` incidence angle of the first hit (nan: no bone).
        calibration: ``(4, 4)`` rigid probe calibration used to write ``poses.csv``.
        visible_mesh: the visible ground-truth surface (open mesh, mm).
        closed_mesh: the input closed mesh.
        config: the configuration used.
    """

    sweep: Sweep
    true_image_to_world: np.ndarray
    true_masks: np.ndarray
    pred_masks: np.ndarray
    surface_depth_mm: np.ndarray
    incidence_deg: np.ndarray
    calibration: np.ndarray
    visible_mesh: trimesh.Trimesh
    closed_mesh: trimesh.Trimesh
    config: SimulationConfig
    info: dict[str, Any] = field(default_factory=dict)

    def true_sweep(self) -> Sweep:
        """The same frames with the exact poses and the true masks."""
        return self.sweep.replace(image_to_world=self.true_image_to_world, masks=self.true_masks)

    def true_positions(self, frame_index: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """``(N, 3)`` mm: where the pixels ``pixel`` ``(N, 2)`` (column, row) of the frames
        ``frame_index`` ``(N,)`` lie under the exact poses; compounded with the recorded poses
        they are off by the tracking error."""
        p2w = self.true_sweep().pixel_to_world()
        out = np.empty((len(pixel), 3))
        for f in np.unique(frame_index):
            rows = frame_index == f
            out[rows] = pixels_to_world(p2w[f], pixel[rows, 0], pixel[rows, 1])
        return out

    def write(self, folder: str | os.PathLike) -> Path:
        """Write the sweep folder (see :func:`write_simulation`)."""
        return write_simulation(self, folder)


# ------------------------------------------------------------------------------------------------
# helpers


def _smooth_noise(rng: np.random.Generator, n: int, sigma: float, dims: int = 1) -> np.ndarray:
    """``(n, dims)`` Gaussian-filtered white noise rescaled to unit standard deviation."""
    white = rng.standard_normal((n, dims))
    if sigma <= 0 or n < 2:
        return white
    sm = ndimage.gaussian_filter1d(white, sigma, axis=0, mode="reflect")
    std = sm.std(axis=0, keepdims=True)
    return sm / np.where(std > 0, std, 1.0)


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
    speed = 1.0 + cfg.speed_variation * _smooth_noise(rng, n, sigma=max(1.0, n / 10))[:, 0]
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

    slow = np.tanh(_smooth_noise(rng, n, sigma=max(1.0, n / 8), dims=2))  # within ±1: amplitudes are maxima
    jit_sigma = 2.0
    jt = _smooth_noise(rng, n, jit_sigma, dims=3) * cfg.jitter_mm
    jr = _smooth_noise(rng, n, jit_sigma, dims=3) * cfg.jitter_deg
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


# ------------------------------------------------------------------------------------------------
# beams, images, masks


class _Slicer:
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


def _incidence(arrays: MeshArrays, face: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """Incidence angle (degrees) of the beam on the hit faces; nan where no hit; > 90 for a back
    face (the probe inside the bone)."""
    out = np.full(len(face), np.nan)
    ok = face >= 0
    cos = -(arrays.normals[face[ok]] @ beam)
    out[ok] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def _speckle(rng: np.random.Generator, shape: tuple[int, int], cfg: SimulationConfig) -> np.ndarray:
    """Rayleigh-distributed amplitude speckle with mean 1, correlated like a PSF."""
    sig = (cfg.speckle_axial_mm / cfg.spacing_mm, cfg.speckle_lateral_mm / cfg.spacing_mm)
    re = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), sig, truncate=2.5)
    im = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), sig, truncate=2.5)
    amp = np.hypot(re, im)
    return amp / max(float(amp.mean()), 1e-12)


@dataclass
class _Fascia:
    depth: float
    amp: float
    wavelength: float
    phase: float
    drift: float
    strength: float


def _make_fascia(rng: np.random.Generator, cfg: SimulationConfig) -> list[_Fascia]:
    out = []
    lo, hi = 2.0, cfg.tissue_depth_mm + 12.0
    for _ in range(cfg.n_fascia):
        out.append(_Fascia(depth=float(rng.uniform(lo, hi)), amp=float(rng.uniform(0.3, 2.0)),
                           wavelength=float(rng.uniform(20, 60)), phase=float(rng.uniform(0, 2 * np.pi)),
                           drift=float(rng.uniform(-0.02, 0.02)), strength=float(rng.uniform(0.6, 1.1))))
    return out


def fascia_depths(fascia: list[_Fascia], xs: np.ndarray, k: int) -> np.ndarray:
    """``(n_fascia, W)`` depth (mm) of each fascia line at lateral positions ``xs`` in frame ``k``."""
    if not fascia:
        return np.zeros((0, len(xs)))
    return np.stack([f.depth + f.amp * np.sin(2 * np.pi * xs / f.wavelength + f.phase + f.drift * k)
                     for f in fascia])


def bmode_image(depth: np.ndarray, incidence: np.ndarray, fascia_y: np.ndarray,
                fascia: list[_Fascia], cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
    """One B-mode-like frame ``(H, W)`` uint8 from the first-hit depth/incidence per beam."""
    h, w = cfg.height_px, cfg.width_px
    y = ((np.arange(h) + 0.5) * cfg.spacing_mm)[:, None]
    # tissue texture: smooth brightness variations over a few mm (made at 1/8 resolution)
    small = (max(2, h // 8), max(2, w // 8))
    tex = ndimage.gaussian_filter(rng.standard_normal(small), (2.0 / (8 * cfg.spacing_mm),
                                                               4.0 / (8 * cfg.spacing_mm)))
    tex = tex / max(float(tex.std()), 1e-12)
    tex = ndimage.zoom(tex, (h / small[0], w / small[1]), order=1)[:h, :w]
    tissue = np.clip(0.33 * (1.0 + 0.2 * tex), 0.12, None)
    for f, fy in zip(fascia, fascia_y):
        tissue = tissue + 0.9 * f.strength * np.exp(-0.5 * ((y - fy[None, :]) / 0.15) ** 2)
    tissue = tissue + 0.7 * np.exp(-0.5 * ((y - 0.45) / 0.1) ** 2)  # skin line
    tissue = tissue * np.exp(-0.012 * y)  # attenuation left after time-gain compensation
    blocked = np.isfinite(depth) & (np.nan_to_num(incidence, nan=180.0) < 90.0)
    d = np.where(blocked, depth, np.inf)[None, :]
    shadow = cfg.shadow_level + (1.0 - cfg.shadow_level) / (1.0 + np.exp((y - d - 0.35) / 0.12))
    shadow = ndimage.gaussian_filter1d(shadow, 0.4 / cfg.spacing_mm, axis=1, mode="nearest")  # beam width
    speckle = _speckle(rng, (h, w), cfg)
    intensity = tissue * shadow * (0.35 + 0.65 * speckle)  # speckle partly smoothed, as scanners do
    cos = np.cos(np.deg2rad(np.nan_to_num(incidence, nan=90.0)))
    vis = blocked & (np.nan_to_num(incidence, nan=180.0) <= cfg.max_incidence_deg)
    amp = np.where(vis, 2.6 * np.clip(cos, 0, 1) ** 1.5, 0.0)[None, :]
    below = np.clip(y - d, 0.0, None)
    profile = np.exp(-0.5 * ((y - d) / 0.18) ** 2) + 0.3 * np.exp(-below / 0.5) * (y > d)
    echo_speckle = 1.0 + 0.35 * (speckle - 1.0)
    intensity = intensity + amp * profile * echo_speckle
    gain = 10.0
    out = 255.0 * np.log1p(gain * intensity) / np.log1p(gain * 3.0)
    out[y[:, 0] < 0.25] *= 0.15  # coupling gel above the skin line
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _runs_mask(rng: np.random.Generator, n: int, fraction: float, mean_len: float) -> np.ndarray:
    """``(n,)`` bool, True inside random runs covering about ``fraction`` of ``n``."""
    out = np.zeros(n, dtype=bool)
    if fraction <= 0 or n == 0:
        return out
    count = rng.poisson(fraction * n / max(mean_len, 1.0))
    for _ in range(count):
        start = int(rng.integers(0, n))
        length = max(1, int(round(rng.exponential(mean_len))))
        out[start:start + length] = True
    return out


def predicted_mask(rows: np.ndarray, incidence: np.ndarray, fascia_y: np.ndarray,
                   cfg: SimulationConfig, rng: np.random.Generator, offset_px: float = 0.0) -> np.ndarray:
    """A 'predicted' mask ``(H, W)`` with realistic errors from the true rows ``(W,)`` (nan: none),
    its boundary moved ``offset_px`` down the beams."""
    h, w = cfg.height_px, cfg.width_px
    mask = np.zeros((h, w), dtype=bool)
    ok = np.isfinite(rows)
    inc = np.nan_to_num(incidence, nan=90.0)
    # weak oblique echoes fade out between pred_max_incidence and max_incidence
    span = max(cfg.max_incidence_deg - cfg.pred_max_incidence_deg, 1e-6)
    p_drop = np.clip((inc - cfg.pred_max_incidence_deg) / span, 0.0, 1.0)
    ok &= rng.random(w) >= p_drop
    ok &= ~_runs_mask(rng, w, cfg.pred_gap_fraction, cfg.pred_gap_mean_mm / cfg.spacing_mm)
    jitter = _smooth_noise(rng, w, sigma=3.0)[:, 0] * cfg.pred_jitter_px + rng.normal(0, cfg.pred_bias_px) \
        if (cfg.pred_jitter_px > 0 or cfg.pred_bias_px > 0) else np.zeros(w)
    if cfg.pred_beam_noise_mm > 0:
        jitter = jitter + rng.normal(0.0, cfg.pred_beam_noise_mm / cfg.spacing_mm, w)
    if cfg.pred_fp_fraction > 0:  # the surface missed, a false echo in its shadow instead
        false = ok & (rng.random(w) < cfg.pred_fp_fraction)
        jitter = jitter + np.where(false, rng.uniform(0.0, cfg.pred_fp_depth_mm / cfg.spacing_mm, w), 0.0)
    cols = np.flatnonzero(ok)
    top = np.rint(rows[cols] + jitter[cols] + offset_px).astype(np.int64)
    for t in range(max(1, cfg.pred_thickness_px)):
        r = top + t
        good = (r >= 0) & (r < h)
        mask[r[good], cols[good]] = True
    for _ in range(rng.poisson(cfg.pred_fp_per_frame)):
        length = max(2, int(round(rng.uniform(1.0, 4.0) / cfg.spacing_mm)))
        c0 = int(rng.integers(0, max(1, w - length)))
        cs = np.arange(c0, min(w, c0 + length))
        vis = np.flatnonzero(np.isfinite(rows))
        kind = rng.random()
        if len(vis) and (kind < 0.5 or len(fascia_y) == 0):
            # just below the bone surface, like a reverberation
            c0 = int(rng.choice(vis))
            cs = np.arange(c0, min(w, c0 + length))
            base = np.interp(cs, vis, rows[vis]) + rng.uniform(1.0, 3.0) / cfg.spacing_mm
        elif len(fascia_y):
            j = int(rng.integers(0, len(fascia_y)))
            base = fascia_y[j, cs] / cfg.spacing_mm - 0.5
        else:
            base = np.full(len(cs), rng.uniform(0.2, 0.9) * h)
        r = np.rint(base).astype(np.int64)
        for t in range(2):
            good = (r + t >= 0) & (r + t < h)
            mask[r[good] + t, cs[good]] = True
    return mask


def add_clutter(masks: np.ndarray, depths: np.ndarray, fascia: list[_Fascia], xs: np.ndarray, frame_mm: float,
                cfg: SimulationConfig, rng: np.random.Generator) -> None:
    """Add to the predicted ``masks`` (F, H, W), in place, the false echoes of real segmentations
    that persist over neighbouring frames (``pred_sheets_per_cm``, ``pred_streaks_per_frame``,
    ``pred_below_per_cm``): sheets in front of the bone, streaks rising from it toward the probe,
    reverberation clusters under it. ``depths`` (F, W): the bone's depth per beam (mm, inf: none);
    ``xs`` (W,): the beams' lateral positions (mm); ``frame_mm``: the mean frame spacing."""
    n, h, w = masks.shape
    sp = cfg.spacing_mm
    length_cm = n * frame_mm / 10.0

    def patch(width_mm: tuple[float, float], run_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        cols = max(2, int(round(rng.uniform(*width_mm) / sp)))
        c0 = int(rng.integers(0, max(1, w - cols)))
        k0 = int(rng.integers(0, n))
        frames = np.arange(k0, min(n, k0 + max(1, int(round(rng.uniform(*run_mm) / frame_mm)))))
        return frames, np.arange(c0, min(w, c0 + cols))

    def label(k: int, cols: np.ndarray, rows_mm: np.ndarray, thick: int = 2) -> None:
        seen = np.isfinite(rows_mm)
        r = np.rint(np.where(seen, rows_mm, -1.0) / sp).astype(np.int64)
        for t in range(thick):
            good = seen & (r + t >= 0) & (r + t < h)
            masks[k, r[good] + t, cols[good]] = True

    for _ in range(rng.poisson(cfg.pred_sheets_per_cm * length_cm)):
        frames, cols = patch((4.0, 20.0), (5.0, 25.0))
        j = int(rng.integers(0, len(fascia))) if fascia else -1
        lift = rng.uniform(3.0, 15.0)
        for k in frames:
            if j >= 0:
                label(k, cols, fascia_depths([fascia[j]], xs, k)[0, cols])
            else:
                label(k, cols, np.where(np.isfinite(depths[k, cols]), depths[k, cols] - lift, np.nan))
    for k in range(n):
        for _ in range(rng.poisson(cfg.pred_streaks_per_frame)):
            bone = np.flatnonzero(np.isfinite(depths[k]))
            if len(bone) == 0:
                break
            c = int(rng.choice(bone))
            cols = np.arange(c, min(w, c + int(rng.integers(1, 4))))
            top = max(0.0, depths[k, c] - rng.uniform(3.0, 20.0))
            rows = np.arange(int(top / sp), int(depths[k, c] / sp))
            for col in cols:
                masks[k, rows[rows < h], col] = True
    for _ in range(rng.poisson(cfg.pred_below_per_cm * length_cm)):
        frames, cols = patch((3.0, 12.0), (3.0, 10.0))
        drop = rng.uniform(2.0, 6.0)
        for k in frames:
            label(k, cols, depths[k, cols] + drop)


# ------------------------------------------------------------------------------------------------
# visible truth


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


# ------------------------------------------------------------------------------------------------


def simulate_sweep(mesh: trimesh.Trimesh, config: SimulationConfig | None = None,
                   progress: Progress = QUIET, calibration: np.ndarray | None = None) -> SimulatedSweep:
    """Simulate a tracked freehand sweep over a closed bone mesh (mm). See the module docstring.

    Raises:
        InputError: for an empty or non-watertight mesh, or a path that misses the bone.
    """
    cfg = config or SimulationConfig()
    if len(mesh.faces) == 0:
        raise InputError("the bone mesh has no faces")
    if not mesh.is_watertight:
        raise InputError("the bone mesh is not closed (watertight); the simulator needs a closed "
                         "surface to tell the bone's inside from its outside")
    rng = np.random.default_rng(cfg.seed)
    arrays = MeshArrays.from_mesh(mesh)
    poses, path_info = plan_path(mesh, cfg, arrays, rng)
    n, h, w = len(poses), cfg.height_px, cfg.width_px
    xs = (np.arange(w) + 0.5) * cfg.spacing_mm
    slicer = _Slicer(arrays, np.asarray(path_info["sweep_axis"]), cfg)
    fascia = _make_fascia(rng, cfg)
    images = np.zeros((n, h, w), dtype=np.uint8)
    true_masks = np.zeros((n, h, w), dtype=bool)
    pred_masks = np.zeros((n, h, w), dtype=bool)
    depths = np.full((n, w), np.inf)
    incid = np.full((n, w), np.nan)
    clutter = np.random.default_rng([cfg.seed, 1])  # its own stream: the other levels stay as they were
    offset_px = (cfg.pred_offset_mm / cfg.spacing_mm * _smooth_noise(clutter, n, sigma=max(1.0, n / 6))[:, 0]
                 if cfg.pred_offset_mm > 0 else np.zeros(n))
    with progress.stage("simulate", n) as advance:
        for k in range(n):
            depth, face = slicer.hits(poses[k], xs)
            inc = _incidence(arrays, face, poses[k, :3, 1])
            depth = np.where(depth < h * cfg.spacing_mm, depth, np.inf)
            inc = np.where(np.isfinite(depth), inc, np.nan)
            depths[k], incid[k] = depth, inc
            visible = np.isfinite(depth) & (np.nan_to_num(inc, nan=180.0) <= cfg.max_incidence_deg)
            rows = np.where(visible, np.floor(depth / cfg.spacing_mm), np.nan)
            cols = np.flatnonzero(visible)
            true_masks[k, rows[cols].astype(np.int64), cols] = True
            fy = fascia_depths(fascia, xs, k)
            images[k] = bmode_image(depth, inc, fy, fascia, cfg, rng)
            pred_masks[k] = predicted_mask(rows, inc, fy, cfg, rng, offset_px[k])
            advance(1)
    add_clutter(pred_masks, depths, fascia, xs, float(path_info["mean_frame_spacing_mm"]), cfg, clutter)
    recorded = perturb_poses(poses, cfg, rng)
    beam_mm = truth_beam_spacing(mesh, cfg)
    dense = _interpolate_poses(poses, beam_mm, w * cfg.spacing_mm)
    beams = np.arange(0.5 * beam_mm, w * cfg.spacing_mm, beam_mm)
    hit: list[np.ndarray] = []
    with progress.stage("visible GT", len(dense)) as advance:
        for q in dense:
            depth, face = slicer.hits(q, beams)
            inc = _incidence(arrays, face, q[:3, 1])
            ok = (depth < h * cfg.spacing_mm) & (np.nan_to_num(inc, nan=180.0) <= cfg.max_incidence_deg)
            hit.append(face[ok])
            advance(1)
    hit_faces = np.unique(np.concatenate(hit)) if hit else np.zeros(0, np.int64)
    visible_mesh = visible_surface(mesh, hit_faces)
    calib = DEFAULT_CALIBRATION if calibration is None else np.asarray(calibration, dtype=np.float64)
    stamps = np.rint(np.arange(n) * 1000.0 / cfg.frame_rate_hz)
    sweep = Sweep(image_to_world=recorded, spacing_mm=(cfg.spacing_mm, cfg.spacing_mm),
                  image_size=(w, h), images=images, masks=pred_masks, timestamps=stamps,
                  frame_names=[f"{int(t)}.png" for t in stamps], pixel_offset=0.5, orientation="MF",
                  source="simulation", meta={"layout": "ultrabones", "calibration": calib})
    kept = np.flatnonzero(~missing_frames(poses, cfg, rng))
    info = dict(path_info)
    info.update(frames=int(len(kept)), missing_frames=int(n - len(kept)),
                visible_faces=int(len(visible_mesh.faces)), truth_beam_mm=beam_mm,
                visible_area_mm2=float(visible_mesh.area) if len(visible_mesh.faces) else 0.0,
                bone_columns_fraction=float(np.isfinite(depths[kept]).mean()),
                true_mask_pixels=int(true_masks[kept].sum()), pred_mask_pixels=int(pred_masks[kept].sum()))
    return SimulatedSweep(sweep=sweep.subset(kept), true_image_to_world=poses[kept],
                          true_masks=true_masks[kept], pred_masks=pred_masks[kept],
                          surface_depth_mm=depths[kept], incidence_deg=incid[kept],
                          calibration=calib, visible_mesh=visible_mesh, closed_mesh=mesh,
                          config=cfg, info=info)


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


SIM_README = """# Simulated tracked ultrasound sweep (ultraboneudf simulate)

Layout of the UltraBones100k sample (`ultraboneudf sweep2points` and `reconstruct` read it as is):

| path | what |
| --- | --- |
| `frames/<t>.png` | B-mode-like frames, 8-bit grey |
| `masks/<t>.png` | "predicted" bone masks with realistic errors (gaps, false positives, jitter) |
| `masks_true/<t>.png` | true masks: the visible bone surface pixel of each scan line |
| `poses.csv`, `calibration.json` | probe poses *with tracking noise* and the probe calibration |
| `truth/poses.csv`, `truth/calibration.json` | the exact poses |
| `gt_visible.ply` | visible ground-truth surface: mesh faces seen by at least one beam (mm) |
| `gt_closed.ply` | the closed bone mesh (mm) |
| `simulation.json` | the simulator's configuration, seed, version and counts |

Pixel → world (mm): `T_track · T_calib · diag(s, s, 1, 1) · [c + 0.5, r + 0.5, 0, 1]ᵀ` with Euler
angles extrinsic xyz in degrees, as in the UltraBones100k sample. The world frame is the mesh's.
"""


def write_simulation(sim: SimulatedSweep, folder: str | os.PathLike) -> Path:
    """Write a simulated sweep in the UltraBones100k layout plus its truth (every file atomic)."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    names = [str(int(t)) for t in sim.sweep.timestamps]
    ultrabones.write(sim.sweep, out, calibration=sim.calibration, names=names,
                     mask_sets={"masks": sim.pred_masks, "masks_true": sim.true_masks})
    ultrabones.write(sim.true_sweep().with_masks(None), out / "truth", calibration=sim.calibration,
                     names=names, write_images=False)
    for name, mesh in (("gt_visible.ply", sim.visible_mesh), ("gt_closed.ply", sim.closed_mesh)):
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
        atomic_write_bytes(out / name, data)
    meta = {"generator": f"ultraboneudf {__version__} simulate", "config": asdict(sim.config),
            "info": sim.info, "pixel_offset": 0.5,
            "files": {"frames": "frames/", "predicted_masks": "masks/", "true_masks": "masks_true/",
                      "poses_recorded": "poses.csv", "poses_true": "truth/poses.csv",
                      "visible_gt": "gt_visible.ply", "closed_gt": "gt_closed.ply"}}
    save_json(json.loads(json.dumps(meta, default=float)), out / "simulation.json")
    atomic_write_bytes(out / "README.md", SIM_README.encode("utf-8"))
    return out


def load_bone_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a closed bone mesh for the simulator (InputError naming the file if unusable)."""
    from ..io import load_mesh  # noqa: PLC0415

    mesh = load_mesh(path)
    if not mesh.is_watertight:
        raise InputError(f"{path}: the mesh is not closed (watertight); the simulator needs a closed "
                         f"bone surface")
    return mesh


__all__ = ["SimulationConfig", "SimulatedSweep", "simulate_sweep", "write_simulation",
           "config_with_noise", "NOISE_PRESETS", "DEFAULT_CALIBRATION", "load_bone_mesh"]
