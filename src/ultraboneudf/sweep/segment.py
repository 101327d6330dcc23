"""Classical bone-surface detection in B-mode frames (no learned weights).

Bone reflects almost all of the ultrasound: on a B-mode frame its surface is a bright, thin echo
*with an acoustic shadow below it*, while soft-tissue interfaces (fascia, the skin line) are bright
lines with tissue speckle below them. The detector scores every pixel by both properties and keeps,
per scan line (image column; the beams run down the columns), the shallowest strong ridge.

Steps, on a copy block-averaged to about ``work_spacing_mm`` (all lengths below are in mm):

1. **Normalise** intensities by the ``norm_percentile`` grey level and smooth with a Gaussian of
   σ = ``smooth_mm``. The soft-tissue level ``T`` is the ``tissue_percentile`` of the result.
2. **Echo** = √(ridge · brightness): ridge = ``max(0, −λ_min(Hessian))·σ²/ridge_ref`` at
   σ = ``ridge_mm`` (any orientation, so sloped bone flanks count); brightness =
   ``(g/T − 1)/bright_ref`` (how much brighter than tissue).
3. **Shadow** = ``(1 − below/above)²``, clipped to [0, 1]: ``below`` is the darker of two
   exponentially weighted means of the scan line from ``shadow_gap_mm`` under the pixel down
   (depth scales ``shadow_decay_mm`` and ``shadow_far_mm``: a shadow right away, or after a grey
   zone as under cartilage); ``above`` is the mean over ``tissue_above_mm`` above the pixel (the
   tissue the beam crossed), at least ``T``. Fascia and the skin line have tissue below: no shadow.
4. **Last echo** = ``1 − (strongest echo within last_echo_mm below)/(own echo)``: a fascia lying
   just above a bone is not the last strong echo of its scan line; the bone is.
5. **Score** = echo · shadow · last echo; rows shallower than ``min_depth_mm`` score 0.
6. **Hysteresis**: pixels scoring ≥ ``low`` connected (8-neighbours) to a pixel ≥ ``high``;
   components narrower than ``min_length_mm`` are dropped.
7. **Per scan line**, among accepted pixels scoring at least ``keep_fraction`` of the line's best,
   the shallowest run; the bone surface is the score maximum of that run (reverberations inside
   the shadow lie deeper and are dropped). The mask marks that pixel (and ``thickness_mm`` below)
   at full resolution.

Every parameter is a field of :class:`BoneDetector`; the defaults were tuned on the UltraBones100k
sample frames and on the simulator's images.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy import ndimage, signal

from ..errors import InputError


@dataclass
class BoneDetector:
    """Tunable classical bone-surface detector; call :meth:`segment` (one frame) or
    :meth:`segment_stack` (many). Lengths in mm, scores and references in [0, 1] intensity units."""

    work_spacing_mm: float = 0.1
    """Pixel size the filters run at (frames are block-averaged down to about this; never up)."""
    norm_percentile: float = 99.5
    """Grey level (percentile of the frame) that maps to intensity 1."""
    smooth_mm: float = 0.15
    """σ of the Gaussian pre-smoothing (speckle suppression)."""
    ridge_mm: float = 0.35
    """σ of the Hessian ridge filter (about the half thickness of a bone echo)."""
    ridge_ref: float = 0.12
    """Ridge response that counts as a full-strength ridge."""
    bright_ref: float = 1.0
    """Echo contrast ``g / T − 1`` (``T``: tissue level) that counts as a full-strength echo."""
    tissue_percentile: float = 75.0
    """Percentile of the smoothed frame taken as the soft-tissue echo level ``T``: echoes are
    bright above ``T``, shadows dark below it."""
    shadow_gap_mm: float = 1.0
    """Gap between the echo and the start of the shadow window (the echo's own thickness)."""
    shadow_decay_mm: float = 6.0
    """Depth scale of the exponential weights of the near shadow window."""
    shadow_far_mm: float = 25.0
    """Depth scale of the far shadow window (bones whose echo is followed by a grey zone before
    the shadow, e.g. under cartilage); the darker of the two windows counts."""
    tissue_above_mm: float = 5.0
    """Depth of the window above a pixel whose mean is the tissue reference of its shadow."""
    last_echo_mm: float = 8.0
    """A pixel loses its score when a stronger echo lies within this depth below it."""
    shadow_min_mm: float = 2.0
    """Minimum depth left below a pixel for a shadow to be judged; deeper pixels score 0."""
    shadow_power: float = 2.0
    """Exponent of the shadow score (higher = stricter)."""
    high: float = 0.5
    """Hysteresis: seed threshold on the score."""
    low: float = 0.12
    """Hysteresis: growth threshold on the score."""
    keep_fraction: float = 0.5
    """Per scan line, accepted pixels scoring at least this fraction of the line's best are
    "strong"; the shallowest strong run is the bone (deeper ones are reverberations)."""
    min_length_mm: float = 3.0
    """Drop accepted components narrower (laterally) than this."""
    min_depth_mm: float = 1.0
    """Ignore the top of the frame (probe face, skin line) down to this depth."""
    thickness_mm: float = 0.0
    """Extra mask thickness below the detected surface (0: one pixel per scan line)."""

    @classmethod
    def from_options(cls, options: dict[str, Any] | None = None) -> "BoneDetector":
        """Build from ``{field: value}`` (unknown names raise :class:`InputError`)."""
        options = dict(options or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - names)
        if unknown:
            raise InputError(f"unknown detector option(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(names))}")
        return cls(**{k: float(v) for k, v in options.items()})

    # ----------------------------------------------------------------------------------------

    def score(self, image: np.ndarray, spacing_mm: float | tuple[float, float]) -> tuple[np.ndarray, float]:
        """Bone-surface score map at the working resolution: ``(score (h, w), factor)``.

        ``factor`` is the integer block size of the resampling (work pixel = factor × input pixel).
        """
        img = np.asarray(image, dtype=np.float64)
        if img.ndim != 2:
            raise ValueError(f"expected a 2-D frame, got shape {img.shape}")
        sx, sy = (spacing_mm, spacing_mm) if np.isscalar(spacing_mm) else spacing_mm
        s = float(min(sx, sy))
        k = max(1, int(round(self.work_spacing_mm / s)))
        if k > 1:
            h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
            img = img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
        px = s * k  # mm per working pixel
        ref = np.percentile(img, self.norm_percentile)
        img = img / ref if ref > 0 else img
        g = ndimage.gaussian_filter(img, self.smooth_mm / px)
        sig = self.ridge_mm / px
        hxx = ndimage.gaussian_filter(img, sig, order=(0, 2))
        hyy = ndimage.gaussian_filter(img, sig, order=(2, 0))
        hxy = ndimage.gaussian_filter(img, sig, order=(1, 1))
        lam_min = 0.5 * (hxx + hyy) - np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy ** 2)
        ridge = np.clip(-lam_min * sig ** 2 / self.ridge_ref, 0.0, 1.0)
        tissue = max(float(np.percentile(g, self.tissue_percentile)), 1e-3)
        bright = np.clip((g / tissue - 1.0) / self.bright_ref, 0.0, None)
        shadow = self._shadow(g, px, tissue)
        echo = np.sqrt(ridge * bright)
        score = echo * shadow * self._last_echo(echo, px)
        score[: int(np.ceil(self.min_depth_mm / px))] = 0.0
        return score, k

    def _last_echo(self, echo: np.ndarray, px: float) -> np.ndarray:
        """``1 − (strongest echo within last_echo_mm below) / (own echo)``, clipped to [0, 1]:
        bone is the last strong echo of its scan line, a fascia above it is not."""
        gap = max(1, int(round(self.shadow_gap_mm / px)))
        n = max(1, int(round(self.last_echo_mm / px)))
        h = echo.shape[0]
        # max over rows [r + gap, r + gap + n): a forward-looking running maximum
        padded = np.vstack([echo, np.zeros((gap + n, echo.shape[1]))])
        run = ndimage.maximum_filter1d(padded, size=n, axis=0, origin=-(n // 2))
        below = run[gap: gap + h]
        return np.clip(1.0 - below / np.maximum(echo, 1e-6), 0.0, 1.0)

    def _shadow(self, g: np.ndarray, px: float, tissue: float) -> np.ndarray:
        """Shadow score in [0, 1]: darkness below each pixel relative to the tissue above it.

        Below: the mean of the smoothed frame from ``shadow_gap_mm`` under the pixel to the bottom,
        weighted by ``exp(−depth / shadow_decay_mm)``. Reference: the mean over
        ``tissue_above_mm`` above the pixel (the tissue this scan line crossed), at least the frame's
        tissue level. Pixels with less than ``shadow_min_mm`` left below score 0.
        """
        h, w = g.shape
        gap = int(round(self.shadow_gap_mm / px))
        a = np.minimum(np.arange(h) + gap, h - 1)
        below = []
        for decay in (self.shadow_decay_mm, self.shadow_far_mm):
            lam = float(np.exp(-px / decay))
            s_acc = signal.lfilter([1.0], [1.0, -lam], g[::-1], axis=0)[::-1]
            w_acc = signal.lfilter([1.0], [1.0, -lam], np.ones((h, 1)), axis=0)[::-1]
            below.append(s_acc[a] / w_acc[a])
        below = np.minimum(below[0], below[1])
        cs = np.vstack([np.zeros((1, w)), np.cumsum(g, axis=0)])
        top = int(np.ceil(self.min_depth_mm / px))
        n_above = max(1, int(round(self.tissue_above_mm / px)))
        rows = np.arange(h)
        b = np.clip(rows - gap, top, h)
        a2 = np.clip(b - n_above, top, h)
        cnt = (b - a2)[:, None]
        above = np.where(cnt >= max(1, n_above // 4), (cs[b] - cs[a2]) / np.maximum(cnt, 1), tissue)
        ref = np.maximum(above, tissue)
        shadow = np.clip(1.0 - below / ref, 0.0, 1.0) ** self.shadow_power
        enough = (h - np.arange(h) - gap) >= max(1, int(round(self.shadow_min_mm / px)))
        return np.where(enough[:, None], shadow, 0.0)

    def surface_rows(self, image: np.ndarray, spacing_mm: float | tuple[float, float]) -> np.ndarray:
        """Per scan line (column of ``image``), the row (float, input pixels) of the detected bone
        surface, NaN where none: ``(W,)``."""
        score, k = self.score(image, spacing_mm)
        sx, sy = (spacing_mm, spacing_mm) if np.isscalar(spacing_mm) else spacing_mm
        px = float(min(sx, sy)) * k
        strong = score >= self.high
        weak = score >= self.low
        labels, n = ndimage.label(weak, structure=np.ones((3, 3), bool))
        if n == 0:
            return np.full(np.asarray(image).shape[1], np.nan)
        seeded = np.zeros(n + 1, bool)
        seeded[np.unique(labels[strong])] = True
        seeded[0] = False
        # lateral extent of each component
        slices = ndimage.find_objects(labels)
        min_cols = self.min_length_mm / px
        for i, sl in enumerate(slices, start=1):
            if sl is not None and seeded[i] and (sl[1].stop - sl[1].start) < min_cols:
                seeded[i] = False
        keep = seeded[labels]
        h, w = keep.shape
        kept_score = np.where(keep, score, 0.0)
        col_best = kept_score.max(axis=0)
        # "strong" per scan line: within keep_fraction of the line's best accepted score
        strong_run = keep & (kept_score >= self.keep_fraction * col_best[None, :])
        any_col = strong_run.any(axis=0)
        top = np.argmax(strong_run, axis=0)  # shallowest strong pixel per column
        rows_work = np.full(w, np.nan)
        for c in np.flatnonzero(any_col):
            r0 = r1 = top[c]
            while r1 + 1 < h and keep[r1 + 1, c]:
                r1 += 1
            rows_work[c] = r0 + int(np.argmax(score[r0:r1 + 1, c]))
        # back to input pixels: the centre of the working pixel
        width = np.asarray(image).shape[1]
        cols_in = np.arange(width)
        work_col = np.minimum(cols_in // k, w - 1)
        rows = rows_work[work_col] * k + (k - 1) / 2.0
        rows[cols_in >= w * k] = np.nan
        return rows

    def segment(self, image: np.ndarray, spacing_mm: float | tuple[float, float]) -> np.ndarray:
        """Bone mask ``(H, W)`` bool of one frame: the surface pixel of each scan line where bone
        is found (plus ``thickness_mm`` below it)."""
        img = np.asarray(image)
        rows = self.surface_rows(img, spacing_mm)
        sy = spacing_mm if np.isscalar(spacing_mm) else spacing_mm[1]
        return rows_to_mask(rows, img.shape[0], int(round(self.thickness_mm / float(sy))))

    def segment_stack(self, images: np.ndarray, spacing_mm: np.ndarray,
                      advance: Any = None) -> np.ndarray:
        """Masks ``(F, H, W)`` bool for frames ``(F, H, W)`` with per-frame spacing ``(F, 2)`` mm."""
        images = np.asarray(images)
        sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (len(images), 2))
        out = np.zeros(images.shape, dtype=bool)
        for i in range(len(images)):
            out[i] = self.segment(images[i], tuple(sp[i]))
            if advance is not None:
                advance(1)
        return out


def rows_to_mask(rows: np.ndarray, height: int, thickness_px: int = 0) -> np.ndarray:
    """Mask ``(height, W)`` with pixel ``(round(rows[c]), c)`` (and ``thickness_px`` below) set;
    NaN rows leave the column empty."""
    w = len(rows)
    mask = np.zeros((height, w), dtype=bool)
    ok = np.isfinite(rows)
    cols = np.flatnonzero(ok)
    r = np.clip(np.rint(rows[ok]).astype(np.int64), 0, height - 1)
    for t in range(thickness_px + 1):
        mask[np.clip(r + t, 0, height - 1), cols] = True
    return mask


def segment_bone(image: np.ndarray, spacing_mm: float | tuple[float, float],
                 **options: float) -> np.ndarray:
    """Classical bone mask ``(H, W)`` bool of one B-mode frame; ``options`` are
    :class:`BoneDetector` fields (lengths in mm)."""
    return BoneDetector.from_options(options).segment(image, spacing_mm)


__all__ = ["BoneDetector", "segment_bone", "rows_to_mask"]
