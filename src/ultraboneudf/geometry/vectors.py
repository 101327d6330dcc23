"""Rows of vectors made unit length."""

from __future__ import annotations

import numpy as np

_FLOOR = 1e-300  # any non-zero length divides; a zero row stays zero instead of becoming NaN


def unit_rows(v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) with every non-zero vector along the last axis scaled to unit length; zero
    vectors stay zero (a direction that is not known). A new array; ``v`` is not modified."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), _FLOOR)
