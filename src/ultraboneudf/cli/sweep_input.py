"""The sweep options shared by ``reconstruct`` and ``sweep2points``, and the one flow both use:
read the sweep through its pose chain, segment the bone, compound the points in mm."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..progress import Progress

CHAIN_OPTIONS = ("calibration", "transform", "reference", "image_frame", "transforms")


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
    """``['high=0.4']`` → ``{'high': 0.4}``; errors name the option."""
    out = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"{option} {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise InputError(f"{option} {item!r}: {v!r} is not a number") from None
    return out


def sweep_inputs(args: argparse.Namespace) -> list[Path]:
    """The files the sweep options name (the outputs must not replace them)."""
    named = [getattr(args, "calibration", None), getattr(args, "masks", None),
             *(getattr(args, "transforms", None) or [])]
    segment = getattr(args, "segment", "auto")
    if segment not in ("auto", "masks", "classical"):
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
    if args.segment not in ("auto", "masks", "classical"):
        from ..sweep.learned import LearnedSegmenter, is_model_path

        model = check_input(args.segment, "model file")
        if not is_model_path(str(model)):
            raise InputError(f"--segment {model}: use auto, masks, classical or the path of a TorchScript "
                             f"(.pt) or ONNX (.onnx) model file")
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
    given = [name for name in CHAIN_OPTIONS if getattr(args, name, None)]
    given += [name for name in ("masks", "mask_dir") if getattr(args, name, None) is not None]
    if getattr(args, "segment", "auto") != "auto":
        given.append("segment")
    if getattr(args, "detector", None):
        given.append("detector")
    if getattr(args, "no_align_frames", False):
        given.append("no_align_frames")
    return ["--" + g.replace("_", "-") for g in given]


def read_options(args: argparse.Namespace, path: Path) -> dict[str, Any]:
    """Keyword options for :func:`~ultraboneudf.sweep.read_sweep` from the command line."""
    from ..sweep import detect_layout

    layout = detect_layout(path) if path.exists() else None
    opts: dict[str, Any] = {}
    chain = {name: getattr(args, name) for name in CHAIN_OPTIONS if getattr(args, name, None)}
    if layout == "ultrabones":
        if chain:
            raise InputError(f"{path}: {', '.join('--' + k.replace('_', '-') for k in chain)} "
                             f"{'apply' if len(chain) > 1 else 'applies'} to PLUS/Slicer sequence "
                             f"files; an UltraBones100k folder carries its calibration in "
                             f"calibration.json")
        if args.mask_dir is not None:
            opts["mask_dir"] = args.mask_dir
        return opts
    if args.mask_dir is not None:
        raise InputError(f"{path}: --mask-dir applies to UltraBones100k folders; give --masks")
    if "transforms" in chain:
        if layout != "nrrd":
            raise InputError(f"{path}: --transforms applies to NRRD image sequences (.seq.nrrd); this "
                             f"file holds its own transforms")
        opts["transforms"] = chain.pop("transforms")
    opts.update(chain)
    return opts


@dataclass
class SweepPoints:
    """What :func:`sweep_points` made: the points and how."""

    points: Any                    # CompoundedPoints
    sweep: Any                     # the Sweep as segmented
    masks: np.ndarray
    method: str
    info: dict = field(default_factory=dict)


def sweep_points(path: Path, args: argparse.Namespace, progress: Progress, *, top_only: bool = True,
                 remove_outliers: bool = True, outlier_rule: str = "local", outlier_k: int = 16,
                 outlier_std: float = 2.0, outlier_factor: float = 1.5, frame_step: int = 1) -> SweepPoints:
    """Read a sweep with the command line's options, segment its bone and compound the points.

    Raises :class:`InputError` (one line, naming the file) for a sweep without 3-D extent, for no
    bone found, and for anything its reader rejects.
    """
    from ..sweep import align_frames, read_sweep, segment_sweep, sweep_to_points
    from ..sweep.bone import classical_bone_masks
    from ..sweep.chain import frames_coplanar
    from ..sweep.consistency import drop_unconfirmed_fragments
    from ..sweep.formats.images import load_mask_stack
    from ..sweep.probability import looks_like_bone_map

    sweep = read_sweep(path, progress=progress, **read_options(args, path))
    chain = sweep.meta.get("chain")
    if chain:
        progress.log(f"{path.name}: pose chain {chain['pixel_frame']}→{chain['reference_frame']} = "
                     f"{chain['chain']}"
                     + (f" (calibration {Path(chain['calibration']).name})" if chain.get("calibration") else "")
                     + f"; {chain['frames_used']}/{chain['frames']} frames valid; points in the "
                     f"{chain['reference_frame']} frame")
        for note in sweep.meta.get("chain_notes", []):
            progress.log(f"{path.name}: {note}")
    if sweep.n_frames < 2 or frames_coplanar(sweep.pixel_to_world(), sweep.image_size)[0]:
        how = f" (chain {chain['chain']})" if chain else ""
        what = "has a single frame" if sweep.n_frames < 2 else "has every frame in one plane"
        raise InputError(f"{path}: the sweep {what}{how}, so it has no 3-D extent; check the "
                         f"tracking transforms and --transform/--reference")
    if args.masks is not None:
        sweep = sweep.with_masks(load_mask_stack(args.masks, sweep.n_frames, sweep.image_size,
                                                 [Path(n).stem for n in sweep.frame_names]))
    if frame_step > 1:
        sweep = sweep.subset(np.arange(0, sweep.n_frames, frame_step))
    segment = args.segment
    if segment == "auto":
        segment = "masks" if sweep.masks is not None else "classical"
    info: dict[str, Any] = {"layout": sweep.meta.get("layout"), "frames": sweep.n_frames,
                            "pixel_spacing_mm": np.round(np.median(sweep.spacing_mm, axis=0), 6).tolist(),
                            "shear_deg": round(float(np.median(sweep.shear_deg)), 4) + 0.0}
    if chain:
        info["pose_chain"] = chain
        info["image_orientation"] = sweep.meta.get("file_orientation")
    detector = parse_kv(args.detector)
    if segment == "classical":
        masks, report = classical_bone_masks(sweep, detector, consistency=not args.no_consistency,
                                             progress=progress)
        method = "classical"
        info["segmentation"] = {"method": method, **report.as_dict()}
        progress.log(f"{path.name}: classical segmentation: {report.summary()}")
    else:
        if detector:
            raise InputError(f"--detector applies to the classical detector, not --segment {segment}")
        masks, method = segment_sweep(sweep, segment, None, {"threshold": args.threshold}, progress)
        info["segmentation"] = {"method": method}
    if not masks.any():
        why = ""
        if segment == "classical":
            rep = info["segmentation"]
            if rep["no_tissue_frames"] == sweep.n_frames:
                why = "; no frame images soft tissue (water or gel only)"
                if looks_like_bone_map(sweep.images):
                    why += ("; if the frames are a bone map (dark but for the bone, e.g. a bone "
                            "enhancer's output), give --segment probability")
            elif rep["no_tissue_frames"] or rep["low_confidence_frames"]:
                why = (f"; {rep['no_tissue_frames']} frame(s) image no soft tissue, "
                       f"{rep['low_confidence_frames']} have only weak echoes")
        raise InputError(f"{path}: no bone found in any of the {sweep.n_frames} frames "
                         f"(segmentation: {method}{why})")
    cp = sweep_to_points(sweep.with_masks(masks), segment="masks", top_only=top_only,
                         remove_outliers=remove_outliers, outlier_rule=outlier_rule, outlier_k=outlier_k,
                         outlier_std=outlier_std, outlier_factor=outlier_factor,
                         remove_fragments=False, progress=progress)
    info["fragments"] = None
    if not args.no_consistency:  # here, not in sweep_to_points, for the sidecar's report
        cp, fragments = drop_unconfirmed_fragments(cp, progress, path.name)
        info["fragments"] = fragments.as_dict()
    if frame_step > 1:
        cp.frame_index = cp.frame_index * frame_step
    info["outlier_removal"] = None if not remove_outliers else {
        "rule": outlier_rule, "k": outlier_k,
        **({"factor": outlier_factor} if outlier_rule == "local" else {"std_ratio": outlier_std})}
    if not args.no_align_frames:
        cp, report = align_frames(cp)
        info["alignment"] = report.as_dict()
        progress.log(f"{path.name}: {report.summary()}")
    d = cp.depth_mm
    info["points"] = {"count": len(cp), "frames_with_bone": int(len(np.unique(cp.frame_index))),
                      "depth_mm_median": round(float(np.median(d)), 3),
                      "depth_mm_p10_p90": [round(float(np.percentile(d, 10)), 3),
                                           round(float(np.percentile(d, 90)), 3)]}
    return SweepPoints(cp, sweep, masks, method, info)
