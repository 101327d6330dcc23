"""Smooth random sequences shared by the simulator's stages (a hand's slow drift, a mask boundary's
wobble)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def smooth_noise(rng: np.random.Generator, n: int, sigma: float, dims: int = 1) -> np.ndarray:
    """``(n, dims)`` Gaussian-filtered white noise rescaled to unit standard deviation."""
    white = rng.standard_normal((n, dims))
    if sigma <= 0 or n < 2:
        return white
    sm = ndimage.gaussian_filter1d(white, sigma, axis=0, mode="reflect")
    std = sm.std(axis=0, keepdims=True)
    return sm / np.where(std > 0, std, 1.0)
