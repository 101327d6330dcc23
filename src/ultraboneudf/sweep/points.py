"""The pieces of the sweep front end (:mod:`.front_end`) by themselves: :func:`segment_sweep`
(bone masks by the chosen segmentation), :func:`drop_outliers`; and :func:`sweep_to_points`, the
front end without the frame registration, its options as keywords (masks may be arrays, the
detector a :class:`BoneDetector`), which returns the points with their provenance (frame index,
probe position, beam direction); :func:`points_from_sweep` returns only the ``(N, 3)`` mm array.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import InputError
from ..progress import QUIET, Progress
from .compound import CompoundedPoints
from .consistency import confirmed_by_frames
from .learned import LearnedSegmenter, is_model_path
from .probability import probability_masks
from .model import Sweep
from .outliers import OUTLIER_RULES, outlier_mask
from .formats import read_sweep
from .bone import classical_bone_masks
from .segment import BoneDetector

SEGMENT_CHOICES = ("auto", "masks", "classical", "probability")


def segment_sweep(sweep: Sweep, segment: str = "auto", detector: Mapping[str, Any] | BoneDetector | None = None,
                  model_options: Mapping[str, Any] | None = None,
                  progress: Progress = QUIET) -> tuple[np.ndarray, str]:
    """Bone masks ``(F, H, W)`` for a sweep and the name of the method used.

    ``segment``: ``auto`` (the sweep's masks if it has them, else the classical detector),
    ``masks`` (the sweep's masks; error if none), ``probability`` (the frames are a bone map, e.g. a
    bone enhancer's output: :func:`~.probability.probability_masks` at ``model_options``'
    ``threshold``, 0.5 by default), ``classical``
    (:func:`~ultraboneudf.sweep.bone.classical_bone_masks`: :class:`BoneDetector` with the
    ``detector`` options in the sweep's imaged region, then the frame-to-frame consistency
    filter; as the command line), or the path of a TorchScript/ONNX model file (:class:`LearnedSegmenter`
    with ``model_options``).
    """
    src = sweep.source or "sweep"
    if segment == "auto":
        segment = "masks" if sweep.masks is not None else "classical"
    if segment == "masks":
        if sweep.masks is None:
            raise InputError(f"{src}: the sweep has no bone masks (give masks, or segment with "
                             f"'classical' or a model file)")
        return sweep.masks, "masks"
    if segment not in ("classical", "probability") and not (is_model_path(segment) or Path(segment).is_file()):
        raise InputError(f"unknown segmentation {segment!r}: use auto, masks, classical, probability or "
                         f"the path of a TorchScript/ONNX model file")
    if sweep.images is None:
        raise InputError(f"{src}: the sweep has no B-mode frames to segment")
    if segment == "probability":
        return probability_masks(sweep.images, float((model_options or {}).get("threshold", 0.5)), src), \
            "probability"
    if segment == "classical":
        masks, _ = classical_bone_masks(sweep, detector, progress=progress)
        return masks, "classical"
    model = LearnedSegmenter(segment, **dict(model_options or {}))
    with progress.stage("segment", sweep.n_frames) as advance:
        return model.segment_stack(sweep.images, sweep.spacing_mm, advance), f"model:{segment}"


def sweep_to_points(sweep: Sweep | str | os.PathLike, *, segment: str = "auto",
                    masks: str | os.PathLike | np.ndarray | None = None,
                    detector: Mapping[str, Any] | BoneDetector | None = None,
                    model_options: Mapping[str, Any] | None = None,
                    top_only: bool = True, remove_outliers: bool = True, outlier_rule: str = "local",
                    outlier_k: int = 16, outlier_std: float = 2.0, outlier_factor: float = 1.5,
                    remove_fragments: bool = True, frame_step: int = 1,
                    progress: Progress = QUIET, **read_options: Any) -> CompoundedPoints:
    """Tracked sweep → bone points in world mm, with per-point provenance.

    Args:
        sweep: a :class:`Sweep`, or the path of a sweep folder / sequence file (read with
            :func:`~ultraboneudf.sweep.formats.read_sweep` and ``read_options``).
        segment: ``auto`` | ``masks`` | ``classical`` | ``probability`` | model file path (see
            :func:`segment_sweep`).
        masks: bone masks for the frames (array ``(F, H, W)``, folder of PNGs, ``.npy``/``.npz``),
            overriding the sweep's own.
        detector: :class:`BoneDetector` or its options (``{field: value}``, lengths in mm).
        model_options: options of :class:`LearnedSegmenter` (``threshold``, ``input_size``, …).
        top_only: keep only the shallowest mask pixel of each scan line (the bone surface).
        remove_outliers: drop isolated false detections (:func:`drop_outliers`):
            ``outlier_rule`` ``local`` (local outlier factor over ``outlier_k`` neighbours at least
            ``outlier_factor``; keeps the sparse echoes of steep faces) or ``statistical`` (mean
            neighbour distance beyond ``outlier_std`` standard deviations), except those seen in
            three frames or more outside the bone's shadow.
        remove_fragments: then drop the isolated fragments seen in one or two frames that
            neighbouring frames imaged without finding them
            (:func:`~.consistency.unconfirmed_fragments`, 4 mm).
        frame_step: use every ``frame_step``-th frame.
        progress: progress reporter.

    Raises:
        InputError: naming the file, for unreadable sweeps, bad masks, or no bone found at all.
    """
    from .front_end import SweepOptions, sweep_points  # noqa: PLC0415

    if outlier_rule not in OUTLIER_RULES:
        raise InputError(f"unknown outlier rule {outlier_rule!r}; choose one of {', '.join(OUTLIER_RULES)}")
    if not isinstance(sweep, Sweep):
        if isinstance(masks, (str, os.PathLike)):
            read_options["masks"] = masks
            masks = None
        sweep = read_sweep(sweep, progress=progress, **read_options)
    elif read_options:
        raise TypeError(f"read options {sorted(read_options)} need a path, not a Sweep")
    if isinstance(masks, (str, os.PathLike)):
        from .formats.images import load_mask_stack  # noqa: PLC0415

        sweep = sweep.with_masks(load_mask_stack(masks, sweep.n_frames, sweep.image_size,
                                                 [Path(n).stem for n in sweep.frame_names]))
    elif masks is not None:
        arr = np.asarray(masks)
        if arr.shape != (sweep.n_frames, sweep.height, sweep.width):
            raise InputError(f"masks have shape {arr.shape}, expected "
                             f"({sweep.n_frames}, {sweep.height}, {sweep.width})")
        sweep = sweep.with_masks(arr)
    if isinstance(detector, BoneDetector):
        detector = dataclasses.asdict(detector)
    options = SweepOptions(segment=segment, detector=detector or {}, top_only=top_only,
                           remove_outliers=remove_outliers, outlier_rule=outlier_rule, outlier_k=outlier_k,
                           outlier_std=outlier_std, outlier_factor=outlier_factor,
                           drop_fragments=remove_fragments, frame_step=frame_step, align_frames=False)
    return sweep_points(sweep, options, progress, model_options=model_options).cloud


def drop_outliers(cp: CompoundedPoints, rule: str = "local", k: int = 16, std_ratio: float = 2.0,
                  factor: float = 1.5, progress: Progress = QUIET, source: str = "") -> CompoundedPoints:
    """``cp`` without the points :func:`~.outliers.outlier_mask` removes (``rule``, ``k``,
    ``std_ratio``, ``factor``), giving back those the sweep confirms
    (:func:`~.consistency.confirmed_by_frames`: seen in three frames or more, none in the shadow of
    the points kept); says on ``progress`` how many it gave back, prefixed with ``source``."""
    if len(cp) <= k + 1:
        return cp
    removed = ~outlier_mask(cp.points, rule, k, std_ratio, factor)
    back = confirmed_by_frames(cp, removed)
    if back.any():
        progress.log(f"{source + ': ' if source else ''}kept {int(back.sum())} of the {int(removed.sum())} "
                     "outlying points: seen in three frames or more, none in the bone's shadow")
    return cp.subset(~removed | back)


def points_from_sweep(path: str | os.PathLike, progress: Progress = QUIET, **options: Any) -> np.ndarray:
    """``(N, 3)`` float64 bone points in mm from a sweep folder or sequence file.

    ``options`` are those of :func:`sweep_to_points` (and of the layout's reader). Raises
    :class:`InputError` naming the file for any problem with the sweep.
    """
    return sweep_to_points(path, progress=progress, **options).points
