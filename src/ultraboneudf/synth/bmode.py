"""The simulated B-mode image of one frame, from the first hit of each beam (mm).

Rayleigh speckle (correlated over ``speckle_axial_mm`` × ``speckle_lateral_mm``) on a soft-tissue
background with a skin line and ``n_fascia`` bright fascia lines (bright echoes without shadow: the
detector's hard negatives), depth attenuation, the bone echo (brightness ∝ cos(incidence)^1.5, a
thin band with a short tail) and the shadow below it (``shadow_level`` of the tissue brightness),
log-compressed to 8 bits. The fascia lines drift slowly from frame to frame; the mask errors
(:mod:`.mask_errors`) take some of them for bone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .simulation_config import SimulationConfig


def _speckle(rng: np.random.Generator, shape: tuple[int, int], cfg: SimulationConfig) -> np.ndarray:
    """Rayleigh-distributed amplitude speckle with mean 1, correlated like a PSF."""
    sig = (cfg.speckle_axial_mm / cfg.spacing_mm, cfg.speckle_lateral_mm / cfg.spacing_mm)
    re = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), sig, truncate=2.5)
    im = ndimage.gaussian_filter(rng.standard_normal(shape, dtype=np.float32), sig, truncate=2.5)
    amp = np.hypot(re, im)
    return amp / max(float(amp.mean()), 1e-12)


@dataclass
class Fascia:
    """One fascia line: mean depth (mm), sinusoidal wobble across the image (amplitude mm,
    wavelength mm, phase rad), drift of that phase per frame (rad) and echo strength (relative)."""

    depth: float
    amp: float
    wavelength: float
    phase: float
    drift: float
    strength: float


def make_fascia(rng: np.random.Generator, cfg: SimulationConfig) -> list[Fascia]:
    """The sweep's ``cfg.n_fascia`` fascia lines, at depths between 2 mm and ``tissue_depth_mm``
    + 12 mm."""
    out = []
    lo, hi = 2.0, cfg.tissue_depth_mm + 12.0
    for _ in range(cfg.n_fascia):
        out.append(Fascia(depth=float(rng.uniform(lo, hi)), amp=float(rng.uniform(0.3, 2.0)),
                          wavelength=float(rng.uniform(20, 60)), phase=float(rng.uniform(0, 2 * np.pi)),
                          drift=float(rng.uniform(-0.02, 0.02)), strength=float(rng.uniform(0.6, 1.1))))
    return out


def fascia_depths(fascia: list[Fascia], xs: np.ndarray, k: int) -> np.ndarray:
    """``(n_fascia, W)`` depth (mm) of each fascia line at lateral positions ``xs`` in frame ``k``."""
    if not fascia:
        return np.zeros((0, len(xs)))
    return np.stack([f.depth + f.amp * np.sin(2 * np.pi * xs / f.wavelength + f.phase + f.drift * k)
                     for f in fascia])


def bmode_image(depth: np.ndarray, incidence: np.ndarray, fascia_y: np.ndarray,
                fascia: list[Fascia], cfg: SimulationConfig, rng: np.random.Generator) -> np.ndarray:
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
