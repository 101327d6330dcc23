"""Classical bone-surface detection in B-mode frames (no learned weights).

Bone reflects almost all of the ultrasound: on a B-mode frame its surface is a bright, thin echo
*with an acoustic shadow below it*, while soft-tissue interfaces (fascia, the skin line) are bright
lines with tissue below them. The detector scores every pixel by both properties and keeps, per
scan line (image column; the beams run down the columns), the *deepest* strong ridge: the last
strong echo before the shadow, not the first bright line.

Steps, inside the imaged region (the screen capture's black border excluded; its top row is depth
0), on a copy block-averaged to about ``work_spacing_mm`` (all lengths below are in mm):

1. **Normalise** intensities by the ``norm_percentile`` grey level and smooth with a Gaussian of
   σ = ``smooth_mm``. The soft-tissue level ``T`` is the ``tissue_percentile`` of the result (both
   from below ``min_depth_mm``). A frame whose ``T`` is below ``min_tissue_ratio`` of its bright
   level images no soft tissue (water, gel): nothing is looked for.
2. **Echo** = √(ridge · brightness): ridge = ``max(0, −λ_min(Hessian))·σ²/ridge_ref`` at
   σ = ``ridge_mm`` (any orientation, so sloped bone flanks count); brightness =
   ``(g/T − 1)/bright_ref`` (how much brighter than tissue).
3. **Shadow** = ``(1 − below/above)²``, clipped to [0, 1]: ``below`` is the darker of two
   exponentially weighted means of the scan line from ``shadow_gap_mm`` under the pixel down
   (depth scales ``shadow_decay_mm`` and ``shadow_far_mm``: a shadow right away, or after a grey
   zone as under cartilage); ``above`` is the mean over ``tissue_above_mm`` above the pixel (the
   tissue the beam crossed), at least ``T``. Fascia and the skin line have tissue below: no shadow.
4. **Last echo** = ``1 − (strongest echo within last_echo_mm below)/(own echo)``: a fascia with
   the deep fascia or the bone below it is not the last strong echo of its scan line; the bone is.
5. **Score** = echo · shadow · last echo; the depth priors ``min_depth_mm`` (probe face, skin,
   subcutaneous layer) and ``max_depth_mm`` zero what lies outside them. The calibration's pixel
   spacing makes these depths exact.
6. **Hysteresis**: pixels scoring ≥ ``low`` connected (8-neighbours) to a pixel ≥ ``high``;
   components narrower than ``min_length_mm`` are dropped.
7. **Per scan line**, among accepted pixels scoring at least ``keep_fraction`` of the line's best,
   the deepest run; the bone surface is the score maximum of that run (reverberations inside the
   shadow are weak and do not count as strong). The mask marks that pixel (and ``thickness_mm``
   below) at full resolution.
8. **Confidence** of the frame = summed score of its detections / imaged scan lines; frames below
   ``min_confidence`` give nothing.

Across frames, :func:`ultraboneudf.sweep.bone.classical_bone_masks` adds the frame-to-frame
consistency filter (:mod:`ultraboneudf.sweep.consistency`). Every parameter is a field of
:class:`BoneDetector`; the defaults were tuned on the UltraBones100k sample frames, the PlusLibData
bone and spine sweeps, and the simulator's images.
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
    last_echo_mm: float = 15.0
    """A pixel loses its score when a stronger echo lies within this depth below it (a superficial
    fascia has the deep fascia and the bone below it; a bone has its shadow)."""
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
    min_depth_mm: float = 3.0
    """Depth prior: no bone shallower than this below the transducer face (the probe face, the
    skin line and the subcutaneous layer). Depths are measured from the top of the imaged region
    in mm, which the calibration's pixel spacing makes exact."""
    max_depth_mm: float = 0.0
    """Depth prior: no bone deeper than this (0: no limit)."""
    min_tissue_ratio: float = 0.08
    """A frame whose soft-tissue level (``tissue_percentile``) is below this fraction of its bright
    level (``norm_percentile``) images water or gel, not tissue: no bone is looked for (an
    N-wire phantom in a water bath has bright wires with dark water above and below them)."""
    min_confidence: float = 0.03
    """Frames whose confidence (:attr:`FrameDetection.confidence`) is below this give no points."""
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
        score, k, _ = self._score(np.asarray(image, dtype=np.float64), spacing_mm)
        return score, k

    def _score(self, img: np.ndarray, spacing_mm: float | tuple[float, float]) -> tuple[np.ndarray, int, float]:
        """``(score, factor, tissue ratio)``: the tissue ratio is the frame's soft-tissue level over
        its bright level (see :attr:`min_tissue_ratio`)."""
        if img.ndim != 2:
            raise ValueError(f"expected a 2-D frame, got shape {img.shape}")
        sx, sy = (spacing_mm, spacing_mm) if np.isscalar(spacing_mm) else spacing_mm
        s = float(min(sx, sy))
        k = max(1, int(round(self.work_spacing_mm / s)))
        if k > 1:
            h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
            img = img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3))
        px = s * k  # mm per working pixel
        # intensity levels from below the depth prior: the probe face and skin line above it are
        # the brightest rows of many frames and would set the scale
        top = min(int(np.ceil(self.min_depth_mm / px)), img.shape[0] - 1)
        ref = np.percentile(img[top:], self.norm_percentile)
        img = img / ref if ref > 0 else img
        g = ndimage.gaussian_filter(img, self.smooth_mm / px)
        sig = self.ridge_mm / px
        hxx = ndimage.gaussian_filter(img, sig, order=(0, 2))
        hyy = ndimage.gaussian_filter(img, sig, order=(2, 0))
        hxy = ndimage.gaussian_filter(img, sig, order=(1, 1))
        lam_min = 0.5 * (hxx + hyy) - np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy ** 2)
        ridge = np.clip(-lam_min * sig ** 2 / self.ridge_ref, 0.0, 1.0)
        tissue_level = float(np.percentile(g[top:], self.tissue_percentile))
        tissue = max(tissue_level, 1e-3)
        bright = np.clip((g / tissue - 1.0) / self.bright_ref, 0.0, None)
        shadow = self._shadow(g, px, tissue)
        echo = np.sqrt(ridge * bright)
        score = echo * shadow * self._last_echo(echo, px)
        score[:top] = 0.0
        if self.max_depth_mm > 0:
            score[int(np.floor(self.max_depth_mm / px)) + 1:] = 0.0
        g_bright = float(np.percentile(g[top:], self.norm_percentile))
        return score, k, tissue_level / max(g_bright, 1e-9)

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

    def detect(self, image: np.ndarray, spacing_mm: float | tuple[float, float],
               region: tuple[int, int, int, int] | None = None) -> "FrameDetection":
        """Detect the bone surface of one frame.

        Args:
            image: ``(H, W)`` B-mode frame.
            spacing_mm: pixel size ``(sx, sy)`` in mm (or one number).
            region: the imaged part of the frame, ``(column, row, width, height)`` in pixels
                (its top row is the transducer face, depth 0); by default the frame's lit part
                (:func:`imaged_region`).

        Returns:
            :class:`FrameDetection`: per scan line the surface row and its score, and the frame's
            confidence.
        """
        img = np.asarray(image, dtype=np.float64)
        full_w = img.shape[1]
        c0, r0, rw, rh = (int(v) for v in (imaged_region(img[None]) if region is None else region))
        rows = np.full(full_w, np.nan)
        scores = np.zeros(full_w)
        crop = img[r0:r0 + rh, c0:c0 + rw]
        if crop.size == 0 or crop.shape[0] < 4 or crop.shape[1] < 4:
            return FrameDetection(rows, scores, 0.0, 0.0)
        score, k, tissue_ratio = self._score(crop, spacing_mm)
        if tissue_ratio < self.min_tissue_ratio:
            return FrameDetection(rows, scores, 0.0, tissue_ratio)
        sx, sy = (spacing_mm, spacing_mm) if np.isscalar(spacing_mm) else spacing_mm
        px = float(min(sx, sy)) * k
        work_rows, work_scores = self._select(score, px)
        # back to input pixels: the centre of the working pixel
        cols_in = np.arange(crop.shape[1])
        work_col = np.minimum(cols_in // k, score.shape[1] - 1)
        inside = cols_in < score.shape[1] * k
        rows[c0 + cols_in[inside]] = r0 + work_rows[work_col[inside]] * k + (k - 1) / 2.0
        scores[c0 + cols_in[inside]] = work_scores[work_col[inside]]
        scores[~np.isfinite(rows)] = 0.0
        confidence = float(scores.sum() / max(1, rw))
        if confidence < self.min_confidence:
            rows[:] = np.nan
            scores[:] = 0.0
        return FrameDetection(rows, scores, confidence, tissue_ratio)

    def _select(self, score: np.ndarray, px: float) -> tuple[np.ndarray, np.ndarray]:
        """Per working column, the bone surface row (NaN where none) and its score.

        Hysteresis on the score, components narrower than ``min_length_mm`` dropped; then per scan
        line the *deepest* run of accepted pixels that is strong (≥ ``keep_fraction`` of the line's
        best): bone is the last strong echo before the shadow, a fascia lies above it and
        reverberations inside the shadow are weak. The surface is the score maximum of that run.
        """
        h, w = score.shape
        rows = np.full(w, np.nan)
        best_scores = np.zeros(w)
        strong = score >= self.high
        weak = score >= self.low
        labels, n = ndimage.label(weak, structure=np.ones((3, 3), bool))
        if n == 0:
            return rows, best_scores
        seeded = np.zeros(n + 1, bool)
        seeded[np.unique(labels[strong])] = True
        seeded[0] = False
        min_cols = self.min_length_mm / px
        for i, sl in enumerate(ndimage.find_objects(labels), start=1):
            if sl is not None and seeded[i] and (sl[1].stop - sl[1].start) < min_cols:
                seeded[i] = False
        keep = seeded[labels]
        kept_score = np.where(keep, score, 0.0)
        col_best = kept_score.max(axis=0)
        strong_run = keep & (kept_score >= self.keep_fraction * col_best[None, :])
        any_col = strong_run.any(axis=0)
        deepest = h - 1 - np.argmax(strong_run[::-1], axis=0)
        for c in np.flatnonzero(any_col):
            r0 = r1 = deepest[c]
            while r0 - 1 >= 0 and keep[r0 - 1, c]:
                r0 -= 1
            r = r0 + int(np.argmax(score[r0:r1 + 1, c]))
            rows[c] = r
            best_scores[c] = score[r, c]
        return rows, best_scores

    def surface_rows(self, image: np.ndarray, spacing_mm: float | tuple[float, float],
                     region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Per scan line (column of ``image``), the row (float, input pixels) of the detected bone
        surface, NaN where none: ``(W,)``."""
        return self.detect(image, spacing_mm, region).rows

    def segment(self, image: np.ndarray, spacing_mm: float | tuple[float, float],
                region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Bone mask ``(H, W)`` bool of one frame: the surface pixel of each scan line where bone
        is found (plus ``thickness_mm`` below it)."""
        img = np.asarray(image)
        rows = self.surface_rows(img, spacing_mm, region)
        sy = spacing_mm if np.isscalar(spacing_mm) else spacing_mm[1]
        return rows_to_mask(rows, img.shape[0], int(round(self.thickness_mm / float(sy))))

    def detect_stack(self, images: np.ndarray, spacing_mm: np.ndarray,
                     region: tuple[int, int, int, int] | None = None,
                     advance: Any = None) -> list["FrameDetection"]:
        """:meth:`detect` on every frame of ``(F, H, W)``; ``region`` as there, or the imaged
        region found in the stack (:func:`imaged_region`)."""
        images = np.asarray(images)
        sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (len(images), 2))
        if region is None:
            region = imaged_region(images)
        out = []
        for i in range(len(images)):
            out.append(self.detect(images[i], tuple(sp[i]), region))
            if advance is not None:
                advance(1)
        return out

    def segment_stack(self, images: np.ndarray, spacing_mm: np.ndarray,
                      advance: Any = None, region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Masks ``(F, H, W)`` bool for frames ``(F, H, W)`` with per-frame spacing ``(F, 2)`` mm
        (frame by frame; :func:`ultraboneudf.sweep.bone.classical_bone_masks` adds the
        frame-to-frame consistency filter)."""
        images = np.asarray(images)
        sp = np.broadcast_to(np.asarray(spacing_mm, dtype=np.float64), (len(images), 2))
        det = self.detect_stack(images, sp, region, advance)
        out = np.zeros(images.shape, dtype=bool)
        for i, d in enumerate(det):
            out[i] = rows_to_mask(d.rows, images.shape[1], int(round(self.thickness_mm / float(sp[i, 1]))))
        return out


@dataclass
class FrameDetection:
    """The classical detector's result for one frame.

    Attributes:
        rows: ``(W,)`` surface row per scan line (input pixels, float), NaN where no bone.
        scores: ``(W,)`` the detector score of that pixel (0 where no bone), in [0, 1].
        confidence: the frame's confidence in [0, 1]: the summed score of its detections over the
            number of imaged scan lines (a frame with a strong echo across the whole image has 1;
            one faint short echo, or nothing, is near 0).
        tissue_ratio: the frame's soft-tissue level over its bright level (see
            :attr:`BoneDetector.min_tissue_ratio`).
    """

    rows: np.ndarray
    scores: np.ndarray
    confidence: float
    tissue_ratio: float


def imaged_region(images: np.ndarray, min_fraction: float = 0.01) -> tuple[int, int, int, int]:
    """The imaged part of a stack of frames ``(F, H, W)``: ``(column, row, width, height)``, the
    bounding box of the columns and rows in which at least ``min_fraction`` of the pixels carry
    signal in some frame. Screen-captured frames (PLUS with a frame grabber) have black borders
    around the ultrasound image; their edges would look like echoes over a shadow. (Water in a
    phantom tank is black too, but echoes cross it somewhere in a sweep.)"""
    im = np.asarray(images)
    lit = im.max(axis=0) > 0
    cols = np.flatnonzero(lit.mean(axis=0) >= min_fraction)
    rows = np.flatnonzero(lit.mean(axis=1) >= min_fraction)
    if len(cols) == 0 or len(rows) == 0:
        return 0, 0, im.shape[2], im.shape[1]
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


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


__all__ = ["BoneDetector", "FrameDetection", "segment_bone", "rows_to_mask", "imaged_region"]
