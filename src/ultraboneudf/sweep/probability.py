"""Frames that are already a bone map: the output of a bone enhancer (PLUS's bone and
transverse-process enhancers) or of a segmentation run elsewhere, dark everywhere but the bone.

Such frames image no soft tissue, so the classical detector, which looks for a bright echo over
tissue with a shadow under it, finds nothing in them; their brightness is the bone's probability.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

_ZERO_SHARE = 0.95  # a bone map leaves nearly every pixel at zero; a B-mode frame of tissue does not


def probability_masks(images: np.ndarray, threshold: float = 0.5, source: str = "sweep") -> np.ndarray:
    """Bone masks ``(F, H, W)`` bool: the pixels of ``images`` ``(F, H, W)`` at or above ``threshold``
    of the full scale (255 for 8-bit frames, 65,535 for 16-bit, 1 for floating-point frames in
    [0, 1], else their largest value)."""
    if not 0.0 < threshold <= 1.0:
        raise InputError(f"{source}: the bone-map threshold must be in (0, 1], got {threshold:g}")
    arr = np.asarray(images)
    if np.issubdtype(arr.dtype, np.integer):
        scale = float(np.iinfo(arr.dtype).max)
    else:
        top = float(np.nanmax(arr)) if arr.size else 0.0
        scale = 1.0 if top <= 1.0 else top
    return arr >= threshold * scale


def looks_like_bone_map(images: np.ndarray) -> bool:
    """Whether most of the frames are dark but for a few bright pixels, as a bone map is (or a
    phantom in water: the caller says which may be meant)."""
    arr = np.asarray(images)
    if arr.size == 0:
        return False
    dark = (arr == 0).mean(axis=tuple(range(1, arr.ndim)))
    return bool(np.median(dark) >= _ZERO_SHARE and arr.max() > 0)
