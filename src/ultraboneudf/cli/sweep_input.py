"""The sweep options of ``reconstruct``, ``sweep2points`` and ``register``: their flags, the checks
made before any frame is read, and their translation to
:class:`~ultraboneudf.sweep.front_end.SweepOptions` for the one front end,
:func:`~ultraboneudf.sweep.front_end.sweep_points`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from ..sweep.front_end import SweepOptions

# the --segment values that name a segmentation rather than a model file (sweep.points'
# SEGMENT_CHOICES, spelled out so that the command line starts without importing the sweep package)
SEGMENT_NAMES = ("auto", "masks", "classical", "probability")


def add_sweep_options(p: argparse.ArgumentParser) -> None:
    """The options that say how to read a tracked sweep and find its bone."""
    g = p.add_argument_group("tracked sweeps (PLUS .mha/.mhd/.igs.nrrd, Slicer .seq.nrrd, UltraBones100k folders)")
    g.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="probe calibration: a PLUS device-set configuration (.xml; its "
                        "CoordinateDefinitions, e.g. Image→Probe) or a 4×4 matrix file (16 numbers "
                        "row-major, or .npy) mapping image pixels to the probe (mm)")
    g.add_argument("--transform", default=None, metavar="NAME",
                   help="per-frame transform the pose chain must use, e.g. ImageToReference or "
                        "ProbeToTracker (default: resolved from the file and the calibration, as PLUS "
                        "does; the log says which chain)")
    g.add_argument("--reference", default=None, metavar="NAME",
                   help="coordinate frame of the output points, e.g. Reference or Tracker (default: "
                        "Reference when the file tracks one, else Tracker)")
    g.add_argument("--image-frame", default=None, metavar="NAME",
                   help="coordinate frame of the stored pixels (default: Image, or the crop frame of "
                        "a cropped sequence)")
    g.add_argument("--transforms", type=Path, action="append", default=None, metavar="FILE",
                   help="transform sequence file(s) for an image sequence without its own transforms "
                        "(3D Slicer saves each transform sequence as a .seq.mha); repeatable")
    g.add_argument("--segment", default="auto",
                   help="auto (the sweep's masks if any, else classical), masks, classical, "
                        "probability (the frames are already a bone map, e.g. the output of PLUS's "
                        "bone enhancer: bone where at least --threshold of full brightness), or the "
                        "path of a TorchScript (.pt) / ONNX (.onnx) model (default: auto)")
    g.add_argument("--masks", type=Path, default=None,
                   help="bone masks for the frames: folder of PNGs (matched by name or order), .npy or "
                        ".npz (F×H×W)")
    g.add_argument("--mask-dir", default=None,
                   help="UltraBones100k layout: sub-folder of masks to use (default: masks)")
    g.add_argument("--detector", action="append", default=[], metavar="KEY=VALUE",
                   help="classical detector option (mm), e.g. --detector min_depth_mm=8; repeatable")
    g.add_argument("--no-consistency", action="store_true",
                   help="keep echoes that no neighbouring frame confirms (by default the classical "
                        "detector drops them point by point, and for every segmentation the isolated "
                        "fragments seen in one or two frames are dropped)")
    g.add_argument("--threshold", type=float, default=0.5,
                   help="learned model or --segment probability: probability threshold (default 0.5)")
    g.add_argument("--no-align-frames", action="store_true",
                   help="keep every frame where the tracker put it (by default each frame is "
                        "registered rigidly to its neighbouring frames, removing per-frame tracking "
                        "error; frames more than a few mm apart are left as tracked anyway)")


def parse_kv(items: list[str], option: str = "--detector") -> dict[str, float]:
    """``['high=0.4']`` → ``{'high': 0.4}``: the classical detector's options, each a number of the
    :class:`~ultraboneudf.sweep.segment.BoneDetector` field it names; errors name the option, the
    key and the problem."""
    import dataclasses

    from ..config import parse_key_values
    from ..sweep.segment import BoneDetector

    types = {f.name: float for f in dataclasses.fields(BoneDetector)}
    return parse_key_values(items, option, types, what="detector option")


def sweep_inputs(args: argparse.Namespace) -> list[Path]:
    """The files the sweep options name (the outputs must not replace them)."""
    named = [getattr(args, "calibration", None), getattr(args, "masks", None),
             *(getattr(args, "transforms", None) or [])]
    segment = getattr(args, "segment", "auto")
    if segment not in SEGMENT_NAMES:
        named.append(Path(segment))
    return [Path(p) for p in named if p is not None]


def check_sweep_options(path: Path, args: argparse.Namespace) -> None:
    """Refuse, before a frame is read, what the sweep options get wrong: a file they name that is
    missing or not a regular file, an unknown ``--detector`` key or a value it cannot take, a
    ``--segment`` model that is not one, ``--masks`` with another number of frames than the sweep
    (:class:`InputError`, one line naming it). Loading a TorchScript model imports PyTorch."""
    from ..io import check_input

    if getattr(args, "calibration", None) is not None:
        check_input(args.calibration, "calibration file")
    for item in getattr(args, "transforms", None) or []:
        check_input(item, "transform sequence file")
    detector = parse_kv(args.detector)
    if detector:
        from ..sweep.segment import BoneDetector

        try:
            BoneDetector.from_options(detector)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise InputError(f"--detector: {exc}") from None
            raise InputError(f"--detector {', '.join(args.detector)}: {exc}") from None
        if args.segment not in ("auto", "classical"):
            raise InputError(f"--detector applies to the classical detector, not --segment {args.segment}")
    if args.segment not in SEGMENT_NAMES:
        from ..sweep.learned import LearnedSegmenter, is_model_path

        model = check_input(args.segment, "model file")
        if not is_model_path(str(model)):
            raise InputError(f"--segment {model}: use auto, masks, classical, probability or the path of a "
                             f"TorchScript (.pt) or ONNX (.onnx) model file")
        LearnedSegmenter(model, threshold=args.threshold)  # a file that is not a model fails here
    if args.masks is not None:
        _check_mask_count(path, check_input(args.masks, "mask file or folder", folder=True))


def _check_mask_count(path: Path, masks: Path) -> None:
    """``--masks`` against the frames the sweep's poses (UltraBones100k) or header (MetaIO)
    declare; other layouts, and MetaIO files with frames marked invalid, are checked once read."""
    from ..sweep import detect_layout
    from ..sweep.formats.images import IMAGE_SUFFIXES

    layout = detect_layout(path)
    stems = None
    if layout == "ultrabones":
        from ..sweep.formats.ultrabones import _read_poses

        stems = _read_poses(path / "poses.csv")[0]
        frames = len(stems)
    elif layout == "metaio":
        from ..sweep.formats.metaio import read_header

        fields, _ = read_header(path)
        if any(v.strip().upper() == "INVALID" for k, v in fields.items() if k.endswith("Status")):
            return
        try:
            frames = int(fields.get("DimSize", "").split()[2])
        except (IndexError, ValueError):
            return
    else:
        return
    if masks.is_dir():
        found = [p for p in masks.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
        if stems is not None and {str(s) for s in stems} <= {p.stem for p in found}:
            return  # matched by name
        count = len(found)
    elif masks.suffix.lower() in (".npy", ".npz"):
        count = _mask_array_frames(masks)
        if count is None:
            return
    else:
        raise InputError(f"{masks}: masks must be a folder of images, .npy or .npz")
    if count != frames:
        raise InputError(f"{masks}: {count} masks for the {frames} frames of {path.name}")


def _mask_array_frames(masks: Path) -> int | None:
    """Frames of a ``.npy`` (or the ``masks`` array of an ``.npz``) mask stack, from its header."""
    import zipfile

    def rows(fh) -> int | None:
        version = np.lib.format.read_magic(fh)
        shape = (np.lib.format.read_array_header_1_0(fh) if version == (1, 0)
                 else np.lib.format.read_array_header_2_0(fh))[0]
        return int(shape[0]) if len(shape) == 3 else None

    try:
        if masks.suffix.lower() == ".npy":
            with open(masks, "rb") as fh:
                return rows(fh)
        with zipfile.ZipFile(masks) as archive, archive.open("masks.npy") as fh:
            return rows(fh)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None  # the reader names what is wrong with it


def sweep_options_given(args: argparse.Namespace) -> list[str]:
    """The sweep options set on the command line (to reject them for a point cloud input)."""
    from ..sweep.front_end import CHAIN_OPTIONS

    given = [name for name in CHAIN_OPTIONS if getattr(args, name, None)]
    given += [name for name in ("masks", "mask_dir") if getattr(args, name, None) is not None]
    if getattr(args, "segment", "auto") != "auto":
        given.append("segment")
    if getattr(args, "detector", None):
        given.append("detector")
    if getattr(args, "no_align_frames", False):
        given.append("no_align_frames")
    return ["--" + g.replace("_", "-") for g in given]


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def read_options(args: argparse.Namespace, path: Path) -> dict[str, Any]:
    """Keyword options for :func:`~ultraboneudf.sweep.read_sweep` from the command line;
    :class:`InputError` naming the flags the sweep's layout does not take."""
    return sweep_options(args).read_kwargs(path, _flag)


def sweep_options(args: argparse.Namespace, **front_end: Any) -> "SweepOptions":
    """The command line's sweep options as :class:`~ultraboneudf.sweep.front_end.SweepOptions`;
    ``front_end``: the options a command sets from its own flags (``sweep2points``: outliers,
    ``top_only``, ``frame_step``)."""
    from ..sweep.front_end import SweepOptions

    consistency = not getattr(args, "no_consistency", False)
    return SweepOptions(
        calibration=getattr(args, "calibration", None), transform=getattr(args, "transform", None),
        reference=getattr(args, "reference", None), image_frame=getattr(args, "image_frame", None),
        transforms=tuple(getattr(args, "transforms", None) or ()), masks=getattr(args, "masks", None),
        mask_dir=getattr(args, "mask_dir", None), segment=getattr(args, "segment", "auto"),
        detector=parse_kv(getattr(args, "detector", None) or []), threshold=getattr(args, "threshold", 0.5),
        confirm_echoes=consistency, drop_fragments=consistency,
        align_frames=not getattr(args, "no_align_frames", False), **front_end)
