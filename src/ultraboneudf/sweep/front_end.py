"""The sweep front end: a tracked sweep → bone points in mm, in one call.

:func:`sweep_points` reads the sweep through its pose chain, segments the bone, compounds the bone
pixels into world millimetres, drops the outliers and the fragments no neighbouring frame confirms,
and registers every frame to its neighbours. :class:`SweepOptions` says how; the command line's
sweep options are a translation of it, and ``reconstruct SWEEP``, ``sweep2points``, ``register``
and the benchmarks all run this one function.

>>> import ultraboneudf
>>> sp = ultraboneudf.sweep_points("sweep_dir")                                    # doctest: +SKIP
>>> rec = ultraboneudf.reconstruct(sp.points, probe_positions=sp.probe_position,
...                                frame_index=sp.frame_index)                      # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..errors import InputError
from ..progress import QUIET, Progress
from .compound import CompoundedPoints, compound
from .model import Sweep
from .outliers import OUTLIER_RULES

CHAIN_OPTIONS = ("calibration", "transform", "reference", "image_frame", "transforms")
"""The options that say how a PLUS or Slicer sequence file's pixels map to the world."""


@dataclass(frozen=True)
class SweepOptions:
    """How :func:`sweep_points` reads a tracked sweep and turns it into bone points. Lengths in mm.

    The defaults are the front end's: the sweep's own masks if it has them, else the classical
    detector; the top boundary of each scan line; outliers, unconfirmed fragments and per-frame
    tracking error removed. ``detector`` is copied on construction (a plain dict).
    """

    # reading the sweep: the pose chain of PLUS/Slicer sequence files (UltraBones100k folders carry
    # theirs in calibration.json)
    calibration: Path | None = None
    """Probe calibration: a PLUS device-set configuration (.xml) or a 4×4 matrix file (image pixels
    → probe, mm)."""
    transform: str | None = None
    """Per-frame transform the pose chain must use (e.g. ``ImageToReference``); ``None``: resolved
    from the file and the calibration, as PLUS does."""
    reference: str | None = None
    """Coordinate frame of the points (e.g. ``Reference``, ``Tracker``); ``None``: ``Reference`` when
    the file tracks one, else ``Tracker``."""
    image_frame: str | None = None
    """Coordinate frame of the stored pixels; ``None``: ``Image``, or a cropped sequence's crop frame."""
    transforms: tuple[Path, ...] = ()
    """Transform sequence files for an NRRD image sequence without its own transforms."""
    masks: Path | None = None
    """Bone masks for the frames (folder of images, .npy or .npz, F×H×W), replacing the sweep's own."""
    mask_dir: str | None = None
    """UltraBones100k folders: the sub-folder of masks to use (``None``: ``masks``)."""
    frame_step: int = 1
    """Use every ``frame_step``-th frame (frame indices stay those of the whole sweep)."""
    # segmentation
    segment: str = "auto"
    """``auto`` (the sweep's masks if any, else ``classical``), ``masks``, ``classical``,
    ``probability`` (the frames are a bone map) or the path of a TorchScript/ONNX model."""
    detector: Mapping[str, float] = field(default_factory=dict)
    """Options of the classical detector (:class:`~ultraboneudf.sweep.segment.BoneDetector`, mm)."""
    threshold: float = 0.5
    """Probability threshold of a model or of ``segment="probability"`` (0 to 1)."""
    confirm_echoes: bool = True
    """Classical detector: drop the echoes that no neighbouring frame continues."""
    # compounding and cleaning
    top_only: bool = True
    """Keep only the shallowest mask pixel of each scan line (the bone surface)."""
    remove_outliers: bool = True
    """Drop isolated false detections (:func:`~ultraboneudf.sweep.points.drop_outliers`)."""
    outlier_rule: str = "local"
    """``local`` (local outlier factor; keeps the sparse echoes of steep faces) or ``statistical``."""
    outlier_k: int = 16
    """Neighbours of the outlier rule."""
    outlier_std: float = 2.0
    """Statistical rule: standard deviations of the mean neighbour distance kept."""
    outlier_factor: float = 1.5
    """Local rule: largest local outlier factor kept."""
    drop_fragments: bool = True
    """Drop the isolated fragments seen in one or two frames that neighbouring frames imaged
    without finding them (:func:`~ultraboneudf.sweep.consistency.drop_unconfirmed_fragments`)."""
    align_frames: bool = True
    """Register every frame rigidly to its neighbouring frames (per-frame tracking error;
    :func:`~ultraboneudf.sweep.align.align_frames`)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "detector", dict(self.detector))
        object.__setattr__(self, "transforms", tuple(Path(p) for p in self.transforms))
        for name in ("calibration", "masks"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, Path(getattr(self, name)))
        if self.outlier_rule not in OUTLIER_RULES:
            raise InputError(f"unknown outlier rule {self.outlier_rule!r}; choose one of {', '.join(OUTLIER_RULES)}")

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON-able values (paths as strings); :meth:`from_dict` reads them back."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Path):
                value = str(value)
            elif f.name == "transforms":
                value = [str(p) for p in value]
            elif f.name == "detector":
                value = dict(value)
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "SweepOptions":
        """Inverse of :meth:`to_dict`; an unknown name raises :class:`InputError`."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise InputError(f"unknown sweep option(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
        return cls(**data)

    def read_kwargs(self, path: Path, name: Callable[[str], str] = str) -> dict[str, Any]:
        """Keyword options of :func:`~ultraboneudf.sweep.read_sweep` for the sweep at ``path``;
        :class:`InputError` for options its layout does not take (each option spelled by ``name``,
        e.g. as a command-line flag)."""
        from .formats import detect_layout

        layout = detect_layout(path) if path.exists() else None
        chain: dict[str, Any] = {k: getattr(self, k) for k in CHAIN_OPTIONS if getattr(self, k)}
        if layout == "ultrabones":
            if chain:
                raise InputError(f"{path}: {', '.join(name(k) for k in chain)} "
                                 f"{'apply' if len(chain) > 1 else 'applies'} to PLUS/Slicer sequence "
                                 f"files; an UltraBones100k folder carries its calibration in "
                                 f"calibration.json")
            return {} if self.mask_dir is None else {"mask_dir": self.mask_dir}
        if self.mask_dir is not None:
            raise InputError(f"{path}: {name('mask_dir')} applies to UltraBones100k folders; give "
                             f"{name('masks')}")
        opts: dict[str, Any] = {}
        if "transforms" in chain:
            if layout != "nrrd":
                raise InputError(f"{path}: {name('transforms')} applies to NRRD image sequences (.seq.nrrd); "
                                 f"this file holds its own transforms")
            opts["transforms"] = list(chain.pop("transforms"))
        opts.update(chain)
        return opts


@dataclass
class SweepPoints:
    """What :func:`sweep_points` made: the bone points (mm, the sweep's world frame) with the
    per-point attributes :func:`~ultraboneudf.reconstruct` uses, what was dropped, and how."""

    cloud: CompoundedPoints
    """The points with their provenance: ``points`` (N, 3) mm, ``frame_index`` (N,),
    ``probe_position`` (N, 3) mm, ``beam_direction`` (N, 3), ``pixel`` (N, 2)."""
    segmentation: str
    """The segmentation used (``masks``, ``classical``, ``probability``, ``model:PATH``)."""
    dropped: dict[str, int]
    """Points removed by each cleaning step: ``outliers``, ``fragments`` (0 when off)."""
    info: dict[str, Any]
    """The record of the run for a sidecar: layout, frames, spacing, pose chain, segmentation,
    fragments, outlier rule, alignment, point statistics."""
    sweep: Sweep = field(repr=False)
    """The sweep as segmented (after ``frame_step``)."""
    masks: np.ndarray = field(repr=False)
    """The bone masks (F, H, W) of ``sweep``."""

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 bone points, mm."""
        return self.cloud.points

    @property
    def probe_position(self) -> np.ndarray:
        """(N, 3) float64 position of the probe that imaged each point, mm."""
        return self.cloud.probe_position

    @property
    def frame_index(self) -> np.ndarray:
        """(N,) int64 frame (of the whole sweep) that imaged each point."""
        return self.cloud.frame_index

    def __len__(self) -> int:
        return len(self.cloud)


def sweep_points(source: Sweep | str | os.PathLike, options: SweepOptions | None = None,
                 progress: Progress = QUIET, *, model_options: Mapping[str, Any] | None = None) -> SweepPoints:
    """A tracked sweep → bone points in mm: read → segment → compound → drop outliers → drop
    unconfirmed fragments → register frames, as ``options`` (:class:`SweepOptions`, its defaults
    when ``None``) say.

    ``source`` is a sweep folder or sequence file (PLUS .mha/.mhd/.igs.nrrd, Slicer .seq.nrrd,
    UltraBones100k folder), or a :class:`Sweep` in memory (then no pose-chain option nor
    ``mask_dir`` may be set).
    ``model_options``: further options of a learned model (:class:`~.learned.LearnedSegmenter`)
    beside ``options.threshold``.

    Raises :class:`InputError` (one line, naming the file) for a sweep without 3-D extent, for no
    bone found, and for anything its reader rejects.
    """
    o = options if options is not None else SweepOptions()
    if isinstance(source, Sweep):
        given = [k for k in (*CHAIN_OPTIONS, "mask_dir") if getattr(o, k)]
        if given:
            raise TypeError(f"sweep options {given} read a sweep from a file, not a Sweep in memory")
        sweep, name, where = source, source.source or "sweep", source.source or "sweep"
    else:
        from .formats import read_sweep

        path = Path(source)
        sweep, name, where = read_sweep(path, progress=progress, **o.read_kwargs(path)), path.name, str(path)
    chain = sweep.meta.get("chain")
    _check_extent(sweep, chain, where)
    if o.masks is not None:
        from .formats.images import load_mask_stack

        sweep = sweep.with_masks(load_mask_stack(o.masks, sweep.n_frames, sweep.image_size,
                                                 [Path(n).stem for n in sweep.frame_names]))
    if o.frame_step > 1:
        sweep = sweep.subset(np.arange(0, sweep.n_frames, int(o.frame_step)))
    info: dict[str, Any] = {"layout": sweep.meta.get("layout"), "frames": sweep.n_frames,
                            "pixel_spacing_mm": np.round(np.median(sweep.spacing_mm, axis=0), 6).tolist(),
                            "shear_deg": round(float(np.median(sweep.shear_deg)), 4) + 0.0}
    if chain:
        progress.log(f"{name}: pose chain {chain['pixel_frame']}→{chain['reference_frame']} = "
                     f"{chain['chain']}"
                     + (f" (calibration {Path(chain['calibration']).name})" if chain.get("calibration") else "")
                     + f"; {chain['frames_used']}/{chain['frames']} frames valid; points in the "
                     f"{chain['reference_frame']} frame")
        for note in sweep.meta.get("chain_notes", []):
            progress.log(f"{name}: {note}")
        info["pose_chain"] = chain
        info["image_orientation"] = sweep.meta.get("file_orientation")
    masks, method, info["segmentation"] = _segment(sweep, o, name, where, progress, model_options)
    with progress.stage("compound", sweep.n_frames) as advance:
        cp = compound(sweep, masks, top_only=o.top_only, advance=advance)
    if len(cp) == 0:
        raise InputError(f"{where}: no bone found in any of the {sweep.n_frames} frames (segmentation: {method})")
    cp, dropped, cleaning = clean_points(cp, o, progress, name, frames=sweep.n_frames, segmentation=method)
    info.update(cleaning)
    d = cp.depth_mm
    info["points"] = {"count": len(cp), "frames_with_bone": int(len(np.unique(cp.frame_index))),
                      "depth_mm_median": round(float(np.median(d)), 3),
                      "depth_mm_p10_p90": [round(float(np.percentile(d, 10)), 3),
                                           round(float(np.percentile(d, 90)), 3)]}
    return SweepPoints(cp, method, dropped, info, sweep, masks)


def clean_points(cp: CompoundedPoints, options: SweepOptions | None = None, progress: Progress = QUIET,
                 source: str = "", *, frames: int | None = None, segmentation: str | None = None
                 ) -> tuple[CompoundedPoints, dict[str, int], dict[str, Any]]:
    """The front end's steps after compounding, as ``options`` say: drop the outliers, drop the
    unconfirmed fragments, give the frame indices of the whole sweep back (``frame_step``), register
    the frames. Returns the points, the counts dropped (``outliers``, ``fragments``) and the
    sidecar's record (``fragments``, ``outlier_removal``, ``alignment``). ``source`` prefixes the
    log lines; with ``frames`` and ``segmentation`` the count of points is logged too."""
    from .align import align_frames
    from .consistency import drop_unconfirmed_fragments
    from .points import drop_outliers

    o = options if options is not None else SweepOptions()
    dropped = {"outliers": 0, "fragments": 0}
    info: dict[str, Any] = {"fragments": None}
    if o.remove_outliers:
        before = len(cp)
        cp = drop_outliers(cp, o.outlier_rule, o.outlier_k, o.outlier_std, o.outlier_factor, progress)
        dropped["outliers"] = before - len(cp)
    if frames is not None:
        progress.log(f"{len(cp)} bone points from {frames} frames ({segmentation})")
    if o.drop_fragments:
        cp, fragments = drop_unconfirmed_fragments(cp, progress, source)
        dropped["fragments"] = fragments.removed
        info["fragments"] = fragments.as_dict()
    if o.frame_step > 1:
        cp.frame_index = cp.frame_index * int(o.frame_step)
    info["outlier_removal"] = None if not o.remove_outliers else {
        "rule": o.outlier_rule, "k": o.outlier_k,
        **({"factor": o.outlier_factor} if o.outlier_rule == "local" else {"std_ratio": o.outlier_std})}
    if o.align_frames:
        cp, report = align_frames(cp)
        info["alignment"] = report.as_dict()
        progress.log(f"{source + ': ' if source else ''}{report.summary()}")
    return cp, dropped, info


def _check_extent(sweep: Sweep, chain: dict | None, where: str) -> None:
    """:class:`InputError` for a sweep of one frame or with every frame in one plane."""
    from .chain import frames_coplanar

    if sweep.n_frames < 2 or frames_coplanar(sweep.pixel_to_world(), sweep.image_size)[0]:
        how = f" (chain {chain['chain']})" if chain else ""
        what = "has a single frame" if sweep.n_frames < 2 else "has every frame in one plane"
        raise InputError(f"{where}: the sweep {what}{how}, so it has no 3-D extent; check the "
                         f"tracking transforms and the transform and reference frames")


def _segment(sweep: Sweep, o: SweepOptions, name: str, where: str, progress: Progress,
             model_options: Mapping[str, Any] | None) -> tuple[np.ndarray, str, dict[str, Any]]:
    """The bone masks (F, H, W), the segmentation's name and its record; :class:`InputError` when
    no frame shows bone."""
    from .bone import classical_bone_masks
    from .points import segment_sweep
    from .probability import looks_like_bone_map

    segment = o.segment
    if segment == "auto":
        segment = "masks" if sweep.masks is not None else "classical"
    if segment == "classical":
        masks, report = classical_bone_masks(sweep, o.detector, consistency=o.confirm_echoes, progress=progress)
        method, record = "classical", {"method": "classical", **report.as_dict()}
        progress.log(f"{name}: classical segmentation: {report.summary()}")
    else:
        if o.detector:
            raise InputError(f"detector options apply to the classical detector, not to segmentation {segment}")
        masks, method = segment_sweep(sweep, segment, None, {"threshold": o.threshold, **(model_options or {})},
                                      progress)
        record = {"method": method}
    if not masks.any():
        why = ""
        if segment == "classical":
            if record["no_tissue_frames"] == sweep.n_frames:
                why = "; no frame images soft tissue (water or gel only)"
                if looks_like_bone_map(sweep.images):
                    why += ("; if the frames are a bone map (dark but for the bone, e.g. a bone "
                            "enhancer's output), give --segment probability (in Python, "
                            "SweepOptions(segment=\"probability\"))")
            elif record["no_tissue_frames"] or record["low_confidence_frames"]:
                why = (f"; {record['no_tissue_frames']} frame(s) image no soft tissue, "
                       f"{record['low_confidence_frames']} have only weak echoes")
        raise InputError(f"{where}: no bone found in any of the {sweep.n_frames} frames "
                         f"(segmentation: {method}{why})")
    return masks, method, record
