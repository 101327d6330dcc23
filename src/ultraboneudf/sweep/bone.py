"""Classical bone segmentation of a whole sweep: the per-frame detector, the sweep's imaged region
and calibration priors, per-frame confidence, and the frame-to-frame consistency filter.

>>> masks, report = classical_bone_masks(sweep)              # doctest: +SKIP
>>> cp = sweep_to_points(sweep.with_masks(masks), segment="masks")   # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..progress import QUIET, Progress
from .consistency import consistent_detections
from .model import Sweep
from .segment import BoneDetector, imaged_region, rows_to_mask


@dataclass
class BoneReport:
    """What :func:`classical_bone_masks` found, for logs and sidecars.

    Attributes:
        region_px: the imaged region used ``(column, row, width, height)``.
        confidence: ``(F,)`` per-frame confidence in [0, 1] (see ``FrameDetection``).
        no_tissue_frames: frames skipped because they image no soft tissue (water, gel).
        low_confidence_frames: frames whose detections were dropped for low confidence.
        consistency: what the frame-to-frame filter removed (``None`` when off).
        frames_with_bone: frames that kept at least one surface point.
    """

    region_px: tuple[int, int, int, int]
    confidence: np.ndarray
    no_tissue_frames: int
    low_confidence_frames: int
    consistency: dict | None = None
    frames_with_bone: int = 0

    def as_dict(self) -> dict:
        return {"region_px": list(self.region_px), "frames_with_bone": self.frames_with_bone,
                "confidence_median": float(np.median(self.confidence)) if len(self.confidence) else 0.0,
                "confidence": [round(float(c), 4) for c in self.confidence],
                "no_tissue_frames": self.no_tissue_frames,
                "low_confidence_frames": self.low_confidence_frames,
                "consistency": self.consistency}

    def summary(self) -> str:
        parts = [f"bone in {self.frames_with_bone}/{len(self.confidence)} frames",
                 f"median confidence {np.median(self.confidence):.2f}" if len(self.confidence) else ""]
        if self.no_tissue_frames:
            parts.append(f"{self.no_tissue_frames} frame(s) image no soft tissue (water or gel)")
        if self.low_confidence_frames:
            parts.append(f"{self.low_confidence_frames} frame(s) below the confidence threshold")
        if self.consistency:
            parts.append(f"{self.consistency['removed']} surface point(s) not continued in a "
                         f"neighbouring frame removed")
        return "; ".join(p for p in parts if p)


def sweep_region(sweep: Sweep) -> tuple[int, int, int, int]:
    """The imaged region of a sweep's frames ``(column, row, width, height)``: the lit part of the
    frames, within the calibration's clip rectangle if any. Its top row is the transducer face
    (depth 0): the clip's top when the calibration gives one (what lies below it may be dark
    water), else the first lit row."""
    c0, r0, w, h = imaged_region(sweep.images)
    clip = sweep.meta.get("clip_rectangle_px")
    if clip:
        a0, a1 = max(c0, clip[0]), min(c0 + w, clip[0] + clip[2])
        b0, b1 = clip[1], min(r0 + h, clip[1] + clip[3])
        if a1 > a0 and b1 > b0:
            c0, r0, w, h = a0, b0, a1 - a0, b1 - b0
    return int(c0), int(r0), int(w), int(h)


def classical_bone_masks(sweep: Sweep, detector: Mapping[str, Any] | BoneDetector | None = None,
                         consistency: bool = True, progress: Progress = QUIET) -> tuple[np.ndarray, BoneReport]:
    """Bone masks ``(F, H, W)`` (one surface pixel per scan line) for a sweep of B-mode frames.

    Each frame: :meth:`BoneDetector.detect` inside the imaged region (the calibration's clip
    rectangle and the non-black part of the frames; depth priors count from its top row). Then the
    frame-to-frame consistency filter (:func:`~ultraboneudf.sweep.consistency.consistent_detections`)
    removes surface points no neighbouring frame confirms.
    """
    if sweep.images is None:
        raise InputError(f"{sweep.source or 'sweep'}: the sweep has no B-mode frames to segment")
    det = detector if isinstance(detector, BoneDetector) else BoneDetector.from_options(dict(detector or {}))
    region = sweep_region(sweep)
    with progress.stage("segment", sweep.n_frames) as advance:
        found = det.detect_stack(sweep.images, sweep.spacing_mm, region, advance)
    rows = np.stack([f.rows for f in found])
    conf = np.array([f.confidence for f in found])
    no_tissue = sum(f.tissue_ratio < det.min_tissue_ratio for f in found)
    low = sum(f.tissue_ratio >= det.min_tissue_ratio and f.confidence < det.min_confidence for f in found)
    report = BoneReport(region, conf, int(no_tissue), int(low))
    if consistency and sweep.n_frames > 1:
        rows, cons = consistent_detections(sweep, rows)
        report.consistency = cons.as_dict()
    masks = np.zeros((sweep.n_frames, sweep.height, sweep.width), dtype=bool)
    for i in range(sweep.n_frames):
        masks[i] = rows_to_mask(rows[i], sweep.height,
                                int(round(det.thickness_mm / float(sweep.spacing_mm[i, 1]))))
    report.frames_with_bone = int(masks.any(axis=(1, 2)).sum())
    return masks, report


__all__ = ["classical_bone_masks", "BoneReport", "sweep_region"]
