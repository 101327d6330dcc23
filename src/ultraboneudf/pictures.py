"""What every picture the package draws needs: Pillow, a text font, colour ramps, and the PNG (or
JPEG) bytes written atomically. The distance renders (:mod:`~ultraboneudf.evaluation.render`) and
the sweep figures (:mod:`~ultraboneudf.sweep.figures`) draw with these."""

from __future__ import annotations

import io
import os
from typing import Any, Sequence

import numpy as np

from .errors import InputError
from .io import atomic_write_bytes

Stops = Sequence[tuple[float, tuple[int, int, int]]]
"""A colour ramp: (position in [0, 1], RGB 0–255) pairs, positions increasing."""

MARKER_COLOURS = ((255, 40, 40), (60, 230, 90), (255, 255, 0), (255, 255, 255))
"""Overlay colours kept exact by :func:`png_bytes`'s ``greys`` palette (red, green, yellow, white)."""


def pil() -> tuple[Any, Any, Any]:
    """Pillow's ``Image``, ``ImageDraw`` and ``ImageFont`` modules, or :class:`InputError` saying what
    to install."""
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError:  # pragma: no cover - Pillow is a dependency
        raise InputError("drawing pictures needs Pillow: pip install 'pillow>=10.1'") from None
    return Image, ImageDraw, ImageFont


def text_font(size: int) -> Any:
    """Pillow's default font at ``size`` pixels; its fixed bitmap font where Pillow has no FreeType
    (then ``size`` is ignored)."""
    _, _, ImageFont = pil()
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):
        return ImageFont.load_default()


def ramp(t: np.ndarray, stops: Stops) -> np.ndarray:
    """RGB ``(..., 3)`` float in [0, 255] of ``t`` ``(...)`` clamped to [0, 1], interpolated
    linearly between the ``stops``."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    pos = np.array([s[0] for s in stops], dtype=np.float64)
    rgb = np.array([s[1] for s in stops], dtype=np.float64)
    return np.stack([np.interp(t, pos, rgb[:, c]) for c in range(3)], axis=-1)


def png_bytes(image: Any, max_colours: int | None = None, greys: int | None = None) -> bytes:
    """A PIL image as optimised PNG bytes. ``max_colours``: an adaptive palette of that many
    colours; ``greys``: that many grey levels plus the exact :data:`MARKER_COLOURS`, for marks on
    ultrasound frames, which stay small and keep their thin coloured lines."""
    Image, _, _ = pil()
    if greys:
        levels = np.linspace(0, 255, greys).round().astype(int)
        pal = [c for g in levels for c in (g, g, g)] + [c for rgb in MARKER_COLOURS for c in rgb]
        pal_img = Image.new("P", (1, 1))
        pal_img.putpalette(pal + [0] * (768 - len(pal)))
        image = image.convert("RGB").quantize(palette=pal_img, dither=Image.Dither.NONE)
    elif max_colours:
        image = image.convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE, colors=max_colours)
    buf = io.BytesIO()
    image.save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def save_picture(image: Any, path: str | os.PathLike, max_colours: int | None = None,
                 greys: int | None = None) -> None:
    """Write a PIL image atomically: JPEG (quality 85) when ``path`` ends in ``.jpg``/``.jpeg``,
    else PNG as :func:`png_bytes` makes it."""
    if str(path).lower().endswith((".jpg", ".jpeg")):
        buf = io.BytesIO()
        image.convert("RGB").save(buf, format="JPEG", quality=85, optimize=True)
        data = buf.getvalue()
    else:
        data = png_bytes(image, max_colours, greys)
    atomic_write_bytes(path, data)
