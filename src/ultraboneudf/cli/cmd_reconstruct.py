"""``ultraboneudf reconstruct INPUT -o OUT.ply``: a point cloud file (mm) or a sweep → mesh + sidecar."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..config import PRESETS
from ..io import check_mesh_path, load_points, sha256_file
from ..methods import METHODS
from ..pipeline import reconstruct
from ..progress import Progress

def add_run_options(p: argparse.ArgumentParser, default_preset: str) -> None:
    """Options shared by ``reconstruct`` and ``demo``."""
    p.add_argument("--preset", default=default_preset, choices=sorted(PRESETS),
                   help=f"parameter set (default: {default_preset})")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: auto)")
    p.add_argument("--seed", type=int, default=42, help="random seed (default: 42)")
    p.add_argument("--iters", type=int, default=None, help="training iterations (overrides the preset)")
    p.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config value, e.g. --set loss.lambda_gs=0 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct", help="reconstruct a bone surface mesh from a point cloud or a tracked sweep",
        description="Reconstruct a mesh (mm, input frame) from a point cloud file (.xyz .txt .csv .ply "
                    ".npy .npz, mm) or a tracked sweep (folder, .mha/.mhd, .seq.nrrd). Writes OUT and a "
                    "JSON sidecar OUT.json with the resolved configuration, timings and counts.")
    p.add_argument("input", type=Path, help="point cloud file or sweep")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mesh (.ply, .obj or .stl)")
    p.add_argument("--method", default="ultraboneudf", choices=sorted(METHODS), help="method (default: ultraboneudf)")
    add_run_options(p, "official")
    p.set_defaults(func=run)


def read_input(path: Path, progress: Progress) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (mm) from a cloud file, or compounded from a sweep (a folder or a sequence file), and
    for a sweep the probe position of each point (mm, same frame; ``None`` for a cloud file)."""
    from ..sweep import is_sweep_path, sweep_to_points

    if path.exists() and is_sweep_path(path):
        cp = sweep_to_points(path, progress=progress)
        return cp.points, cp.probe_position
    return load_points(path), None


def run(args: argparse.Namespace) -> int:
    output = check_mesh_path(args.output)
    progress = Progress(quiet=args.quiet)
    points, probe = read_input(args.input, progress)
    overrides = {} if args.iters is None else {"train.iters": args.iters}
    rec = reconstruct(points, preset=args.preset, device=args.device, seed=args.seed, method=args.method,
                      assignments=args.assignments, progress=progress, source=str(args.input),
                      probe_positions=probe, **overrides)
    if rec.mesh is None:
        print(f"ultraboneudf reconstruct: no surface was found in {args.input}; nothing written "
              "(see the loss history with --set train.iters=… or try another preset)", file=sys.stderr)
        return 1
    rec.input = {"path": str(args.input.resolve()), "sha256": sha256_file(args.input)}
    sidecar = rec.save(output)
    t = rec.timings
    progress.log(f"wrote {output} ({rec.counts['vertices']} vertices, {rec.counts['faces']} faces) and "
                 f"{sidecar}; {t['total_s']:.1f} s (preprocess {t['preprocess_s']:.1f}, "
                 f"train {t['train_s']:.1f}, extract {t['extract_s']:.1f}) on {rec.device}")
    for warning in rec.fit_warnings():  # shown even with --quiet: they concern the result
        print(f"ultraboneudf reconstruct: warning: {warning}", file=sys.stderr)
    return 0
