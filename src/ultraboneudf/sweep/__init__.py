"""Tracked freehand ultrasound sweeps → bone point clouds in millimetres.

>>> from ultraboneudf.sweep import SweepOptions, read_sweep, sweep_points
>>> sp = sweep_points("sweep_dir", SweepOptions(segment="classical"))   # doctest: +SKIP
>>> sp.points, sp.frame_index, sp.probe_position, sp.dropped           # doctest: +SKIP

The front end (:func:`sweep_points`, :class:`SweepOptions`, :mod:`.front_end`) runs the pieces below
in order: read, segment, compound, drop outliers, drop unconfirmed fragments, register frames.

Pieces: :class:`Sweep` (frames + poses in memory), readers/writers by layout
(:func:`read_sweep`, :func:`write_sweep`: UltraBones100k folders, PLUS ``.mha``/``.mhd``/``.igs.nrrd``,
Slicer ``.seq.nrrd``), the PLUS pose chain and calibrations (:mod:`.chain`,
:func:`read_calibration`), :class:`BoneDetector` and :func:`classical_bone_masks` (classical
segmentation with the frame-to-frame consistency filter), :class:`LearnedSegmenter`
(TorchScript/ONNX plug-in), :func:`compound` (mask pixels → world mm), outlier removal
(:func:`drop_outliers`, which gives back what :func:`confirmed_by_frames` vouches for) and
:func:`unconfirmed_fragments` (echoes no neighbouring frame confirms),
:func:`align_frames` (each frame rigidly registered to its neighbours against tracking error).
"""

from .align import AlignmentReport, align_frames
from .bone import classical_bone_masks
from .calibration import Calibration, read_calibration
from .compound import CompoundedPoints, compound, top_boundary
from .consistency import confirmed_by_frames, unconfirmed_fragments
from .learned import LearnedSegmenter, load_model
from .model import Sweep, SweepWarning
from .outliers import local_outlier_mask, outlier_mask, radius_outlier_mask, statistical_outlier_mask
from .points import drop_outliers, points_from_sweep, segment_sweep, sweep_to_points
from .front_end import SweepOptions, SweepPoints, clean_points, sweep_points
from .formats import LAYOUTS, detect_layout, is_sweep_path, read_sweep, write_sweep
from .segment import BoneDetector, segment_bone
from .transforms import check_rigid, pixels_to_world, rigid_from_euler

__all__ = [
    "Sweep", "SweepWarning", "read_sweep", "read_calibration", "Calibration", "classical_bone_masks", "write_sweep", "detect_layout", "is_sweep_path", "LAYOUTS",
    "BoneDetector", "segment_bone", "LearnedSegmenter", "load_model", "segment_sweep",
    "CompoundedPoints", "compound", "top_boundary", "outlier_mask", "local_outlier_mask",
    "statistical_outlier_mask", "radius_outlier_mask",
    "sweep_to_points", "points_from_sweep", "rigid_from_euler", "check_rigid", "pixels_to_world",
    "align_frames", "AlignmentReport", "unconfirmed_fragments", "confirmed_by_frames", "drop_outliers",
    "SweepOptions", "SweepPoints", "sweep_points", "clean_points",
]
