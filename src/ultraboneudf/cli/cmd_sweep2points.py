"""``ultraboneudf sweep2points SWEEP -o POINTS``: tracked sweep → bone point cloud in mm."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError
from . import add_overwrite
from .sweep_input import add_sweep_options, check_sweep_options, read_options, sweep_inputs, sweep_options

if TYPE_CHECKING:
    import numpy as np

    from ..sweep.front_end import SweepOptions


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sweep2points", help="tracked ultrasound sweep → bone point cloud (mm)",
        description="Read a tracked sweep (a folder in the UltraBones100k layout: frames/*.png, "
                    "poses.csv, calibration.json; a PLUS .mha/.mhd; a Slicer .seq.nrrd), segment the "
                    "bone in every frame (its masks, the classical detector, or your TorchScript/ONNX "
                    "model), map the bone pixels to world millimetres through the pose and calibration "
                    "chain, and write the point cloud with each point's frame index.")
    p.add_argument("sweep", type=Path, help="sweep folder or sequence file")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output cloud: .ply (x y z + frame, beam, probe), .npz (all arrays), .npy, "
                        ".xyz/.txt/.csv (x y z frame)")
    p.add_argument("--all-pixels", action="store_true",
                   help="keep every mask pixel (default: only the top boundary of each scan line, "
                        "the bone surface)")
    p.add_argument("--no-outliers", action="store_true", help="skip outlier removal")
    p.add_argument("--outlier-rule", choices=("local", "statistical"), default="local",
                   help="outlier removal: 'local' (default) drops points much sparser than their "
                        "neighbours (local outlier factor) and keeps the sparse echoes of steep faces; "
                        "'statistical' drops points whose mean neighbour distance is far above the "
                        "cloud's")
    p.add_argument("--outlier-k", type=int, default=16, help="outlier removal: neighbours (default 16)")
    p.add_argument("--outlier-factor", type=float, default=1.5,
                   help="local rule: largest local outlier factor kept (default 1.5)")
    p.add_argument("--outlier-std", type=float, default=2.0,
                   help="statistical rule: threshold in standard deviations (default 2.0)")
    p.add_argument("--frame-step", type=int, default=1, help="use every N-th frame (default 1)")
    p.add_argument("--overlays", type=Path, default=None,
                   help="also write segmentation overlay contact sheets (PNG) to this folder (a new "
                        "folder, or one of earlier overlays: it is replaced as a whole)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_overwrite(p, "the output cloud, its sidecar and the overlay folder")
    add_sweep_options(p)
    p.set_defaults(func=run)


def _write_overlays(sweep, masks: np.ndarray, folder: Path) -> list[Path]:
    from ..pictures import save_picture
    from ..sweep.figures import contact_sheet, mark_dilation, overlay

    written = []
    per_sheet = 30
    for s in range(0, sweep.n_frames, per_sheet):
        idx = range(s, min(sweep.n_frames, s + per_sheet))
        tiles = [overlay(sweep.images[i], masks[i], dilate=mark_dilation(sweep.width, 320)) for i in idx]
        path = folder / f"overlay_{s // per_sheet:03d}.png"
        save_picture(contact_sheet(tiles, [Path(sweep.frame_names[i]).name for i in idx], columns=6,
                                   tile_width=320), path, greys=64)
        written.append(path)
    return written


def run(args: argparse.Namespace) -> int:
    from ..io import POINT_SUFFIXES, check_input, check_output

    out: Path = args.output
    if out.suffix.lower() not in POINT_SUFFIXES:
        raise InputError(f"{out}: unknown point cloud extension {out.suffix!r}; use one of "
                         f"{', '.join(POINT_SUFFIXES)}")
    if args.frame_step < 1:
        raise InputError(f"--frame-step must be ≥ 1, got {args.frame_step}")
    if args.outlier_k < 1 or not args.outlier_factor > 1.0 or not args.outlier_std > 0:
        raise InputError(f"--outlier-k must be ≥ 1, --outlier-factor > 1 (a surface's points have a "
                         f"factor of about 1) and --outlier-std > 0, got {args.outlier_k}, "
                         f"{args.outlier_factor:g} and {args.outlier_std:g}")
    if not 0 < args.threshold < 1:
        raise InputError(f"--threshold must be a probability between 0 and 1, got {args.threshold:g}")
    inputs = (args.sweep, *sweep_inputs(args))
    check_output(out, inputs=inputs, overwrite=args.overwrite)
    if args.overlays is not None:
        check_output(args.overlays, inputs=(*inputs, out), overwrite=args.overwrite, kind="folder")
    check_input(args.sweep, "sweep", folder=True)
    read_options(args, args.sweep)
    check_sweep_options(args.sweep, args)
    return _run(args, out)


def front_end_options(args: argparse.Namespace) -> "SweepOptions":
    """The front end's options: the sweep options, and this command's own."""
    return sweep_options(args, top_only=not args.all_pixels, remove_outliers=not args.no_outliers,
                         outlier_rule=args.outlier_rule, outlier_k=args.outlier_k, outlier_std=args.outlier_std,
                         outlier_factor=args.outlier_factor, frame_step=args.frame_step)


def _run(args: argparse.Namespace, out: Path) -> int:
    import numpy as np

    from ..io import encode_points, record, sha256_file, write_outputs
    from ..progress import Progress
    from ..sweep.front_end import sweep_points

    progress = Progress(quiet=args.quiet)
    res = sweep_points(args.sweep, front_end_options(args), progress)
    cp, sweep = res.cloud, res.sweep
    meta = record("sweep2points", input={"path": str(args.sweep.resolve()), "sha256": sha256_file(args.sweep)},
                  options={k: str(v) for k, v in sorted(vars(args).items()) if k not in ("func", "output")},
                  sweep=res.info)
    sheets = args.overlays is not None and sweep.images is not None
    overlays = [] if not sheets else [
        (args.overlays, lambda folder: _write_overlays(sweep, res.masks, folder),
         record("sweep2points", overlays_of=out.name))]
    write_outputs([(out, encode_points(out, cp), meta)], overlays, overwrite=args.overwrite)
    frames_with_bone = len(np.unique(cp.frame_index))
    lo, hi = cp.points.min(axis=0), cp.points.max(axis=0)
    print(f"sweep2points: {len(cp)} points from {frames_with_bone}/{sweep.n_frames} frames "
          f"(segmentation: {res.segmentation}); extent {np.round(hi - lo, 1).tolist()} mm; wrote {out} and "
          f"its sidecar {out.name}.json")
    if sheets:
        print(f"sweep2points: wrote {-(-sweep.n_frames // 30)} overlay sheet(s) to {args.overlays}")
    elif args.overlays is not None:
        print(f"sweep2points: {args.sweep} has masks but no B-mode frames: no overlay sheets")
    return 0
