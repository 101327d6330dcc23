"""The errors of a real segmentation network, put into the simulator's "predicted" masks.

Per frame (:func:`predicted_mask`): the true surface row per column with a per-frame bias and
smooth boundary jitter (``pred_jitter_px``), ``pred_thickness_px`` thick; gaps
(``pred_gap_fraction`` of the columns in runs of mean ``pred_gap_mean_mm``), weak echoes dropped
above ``pred_max_incidence_deg``, oblique faces' boundary moved out of the bone (``pred_oblique_mm``,
:func:`oblique_offsets`), and ``pred_fp_per_frame`` off-surface false positives (short
segments on fascia or just below the bone, like reverberations). For the ``real`` noise level also
an offset along the beam drifting along the sweep (:func:`boundary_offsets`) and false echoes that
persist over neighbouring frames (:func:`add_clutter`: fascia sheets in front of the bone, streaks
rising from it, reverberation clusters under it), both from their own random stream, so that the
other levels draw what they drew before these existed.
"""

from __future__ import annotations

import numpy as np

from .bmode import Fascia, fascia_depths
from .noise import smooth_noise
from .simulation_config import SimulationConfig


def boundary_offsets(clutter: np.random.Generator, n: int, cfg: SimulationConfig) -> np.ndarray:
    """``(n,)`` px: how far each frame's predicted boundary lies down the beams, drifting smoothly
    along the sweep by about ``pred_offset_mm`` (zeros, drawing nothing, when that is 0)."""
    if cfg.pred_offset_mm <= 0:
        return np.zeros(n)
    return cfg.pred_offset_mm / cfg.spacing_mm * smooth_noise(clutter, n, sigma=max(1.0, n / 6))[:, 0]


def oblique_offsets(incidence: np.ndarray, cfg: SimulationConfig) -> np.ndarray:
    """``(W,)`` px: how far up the beams (toward the probe) each scan line's predicted boundary lies,
    for a face at ``incidence`` (W,) degrees moved ``pred_oblique_mm × (1 − cos incidence)`` out of
    the bone along its normal. A plane moved by δ along its normal moves by δ / cos(incidence) along a
    beam; the cosine is held at 0.25 or more, where a face this steep ends at the bone's silhouette
    and its echo cannot lie farther out."""
    if cfg.pred_oblique_mm <= 0:
        return np.zeros(len(incidence))
    cos = np.clip(np.cos(np.radians(np.nan_to_num(incidence, nan=0.0))), 0.25, 1.0)
    return -cfg.pred_oblique_mm * (1.0 - cos) / cos / cfg.spacing_mm


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
    jitter = smooth_noise(rng, w, sigma=3.0)[:, 0] * cfg.pred_jitter_px + rng.normal(0, cfg.pred_bias_px) \
        if (cfg.pred_jitter_px > 0 or cfg.pred_bias_px > 0) else np.zeros(w)
    if cfg.pred_beam_noise_mm > 0:
        jitter = jitter + rng.normal(0.0, cfg.pred_beam_noise_mm / cfg.spacing_mm, w)
    if cfg.pred_fp_fraction > 0:  # the surface missed, a false echo in its shadow instead
        false = ok & (rng.random(w) < cfg.pred_fp_fraction)
        jitter = jitter + np.where(false, rng.uniform(0.0, cfg.pred_fp_depth_mm / cfg.spacing_mm, w), 0.0)
    cols = np.flatnonzero(ok)
    lift = oblique_offsets(inc, cfg)
    top = np.rint(rows[cols] + jitter[cols] + offset_px + lift[cols]).astype(np.int64)
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


def add_clutter(masks: np.ndarray, depths: np.ndarray, fascia: list[Fascia], xs: np.ndarray, frame_mm: float,
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
