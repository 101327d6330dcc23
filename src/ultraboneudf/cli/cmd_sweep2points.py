"""``ultraboneudf sweep2points SWEEP -o POINTS``: tracked sweep → bone point cloud in mm."""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..progress import Progress
from .sweep_input import add_sweep_options, sweep_points

POINT_SUFFIXES = (".ply", ".npz", ".npy", ".xyz", ".txt", ".csv")


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
    p.add_argument("--no-outliers", action="store_true", help="skip statistical outlier removal")
    p.add_argument("--outlier-k", type=int, default=16, help="outlier removal: neighbours (default 16)")
    p.add_argument("--outlier-std", type=float, default=2.0,
                   help="outlier removal: threshold in standard deviations (default 2.0)")
    p.add_argument("--frame-step", type=int, default=1, help="use every N-th frame (default 1)")
    p.add_argument("--overlays", type=Path, default=None,
                   help="also write segmentation overlay contact sheets (PNG) to this folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_sweep_options(p)
    p.set_defaults(func=run)


def encode_points(path: Path, cp) -> bytes:
    """Bytes of the point file for ``path``'s suffix (see ``--output``)."""
    suffix = path.suffix.lower()
    pts = cp.points
    if suffix == ".ply":
        n = len(pts)
        dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("frame", "<i4"),
                          ("beam_x", "<f4"), ("beam_y", "<f4"), ("beam_z", "<f4"),
                          ("probe_x", "<f8"), ("probe_y", "<f8"), ("probe_z", "<f8")])
        rec = np.empty(n, dtype=dtype)
        rec["x"], rec["y"], rec["z"] = pts.T
        rec["frame"] = cp.frame_index
        rec["beam_x"], rec["beam_y"], rec["beam_z"] = cp.beam_direction.T
        rec["probe_x"], rec["probe_y"], rec["probe_z"] = cp.probe_position.T
        header = ["ply", "format binary_little_endian 1.0",
                  "comment bone points compounded from a tracked ultrasound sweep (ultraboneudf), mm",
                  "comment frame: source frame index; beam: unit beam direction; probe: scan-line origin",
                  f"element vertex {n}", "property double x", "property double y", "property double z",
                  "property int frame", "property float beam_x", "property float beam_y",
                  "property float beam_z", "property double probe_x", "property double probe_y",
                  "property double probe_z", "end_header"]
        return ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()
    if suffix == ".npz":
        buf = io.BytesIO()
        np.savez_compressed(buf, **cp.as_dict())
        return buf.getvalue()
    if suffix == ".npy":
        buf = io.BytesIO()
        np.save(buf, pts)
        return buf.getvalue()
    sep = "," if suffix == ".csv" else " "
    lines = ["x,y,z,frame"] if suffix == ".csv" else []
    lines += [f"{x:.6f}{sep}{y:.6f}{sep}{z:.6f}{sep}{f}" for (x, y, z), f in zip(pts, cp.frame_index)]
    return ("\n".join(lines) + "\n").encode("ascii")


def _write_overlays(sweep, masks: np.ndarray, folder: Path) -> list[Path]:
    from ..sweep.figures import contact_sheet, mark_dilation, overlay, save_png

    if sweep.images is None:
        return []
    written = []
    per_sheet = 30
    for s in range(0, sweep.n_frames, per_sheet):
        idx = range(s, min(sweep.n_frames, s + per_sheet))
        tiles = [overlay(sweep.images[i], masks[i], dilate=mark_dilation(sweep.width, 320)) for i in idx]
        path = folder / f"overlay_{s // per_sheet:03d}.png"
        save_png(contact_sheet(tiles, [Path(sweep.frame_names[i]).name for i in idx], columns=6,
                               tile_width=320), path, greys=64)
        written.append(path)
    return written


def run(args: argparse.Namespace) -> int:
    from ..io import atomic_write_bytes

    progress = Progress(quiet=args.quiet)
    out: Path = args.output
    if out.suffix.lower() not in POINT_SUFFIXES:
        raise InputError(f"{out}: unknown point cloud extension {out.suffix!r}; use one of "
                         f"{', '.join(POINT_SUFFIXES)}")
    if args.frame_step < 1:
        raise InputError(f"--frame-step must be ≥ 1, got {args.frame_step}")
    res = sweep_points(args.sweep, args, progress, top_only=not args.all_pixels,
                       remove_outliers=not args.no_outliers, outlier_k=args.outlier_k,
                       outlier_std=args.outlier_std, frame_step=args.frame_step)
    cp, sweep = res.points, res.sweep
    atomic_write_bytes(out, encode_points(out, cp))
    frames_with_bone = len(np.unique(cp.frame_index))
    lo, hi = cp.points.min(axis=0), cp.points.max(axis=0)
    print(f"sweep2points: {len(cp)} points from {frames_with_bone}/{sweep.n_frames} frames "
          f"(segmentation: {res.method}); extent {np.round(hi - lo, 1).tolist()} mm; wrote {out}")
    if args.overlays is not None:
        written = _write_overlays(sweep, res.masks, args.overlays)
        if written:
            print(f"sweep2points: wrote {len(written)} overlay sheet(s) to {args.overlays}")
    return 0
