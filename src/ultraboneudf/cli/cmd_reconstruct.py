"""``ultraboneudf reconstruct INPUT -o OUT.ply``: a point cloud file (mm) or a sweep → mesh + sidecar."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..config import DEFAULT_PRESET, PRESET_HELP, PRESETS, UNITS_MM
from ..errors import InputError
from ..methods import NAMES
from .sweep_input import add_sweep_options, sweep_options_given, sweep_points

if TYPE_CHECKING:
    import numpy as np

    from ..progress import Progress

def _at_least(low: int):
    """An argparse type: an integer ≥ ``low`` (a usage error, exit 2, otherwise)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{value} is below {low}")
        return value
    return parse


def add_run_options(p: argparse.ArgumentParser, default_preset: str) -> None:
    """Options shared by ``reconstruct`` and ``demo``."""
    p.add_argument("--preset", default=default_preset, choices=list(PRESETS),
                   help="parameter set: " + "; ".join(f"{k}: {v}" for k, v in PRESET_HELP.items())
                        + f" (default: {default_preset})")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: auto)")
    p.add_argument("--seed", type=_at_least(0), default=42, help="random seed, 0 or more (default: 42)")
    p.add_argument("--iters", type=_at_least(1), default=None,
                   help="training iterations, 1 or more (overrides the preset)")
    p.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config value, e.g. --set loss.lambda_gs=0 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct", help="reconstruct a bone surface mesh from a point cloud or a tracked sweep",
        description="Reconstruct a mesh (mm, input frame) from a point cloud file (.xyz .txt .csv .ply "
                    ".npy .npz, mm) or a tracked sweep (folder, PLUS .mha/.mhd/.igs.nrrd with its "
                    "--calibration, Slicer .seq.nrrd). Writes OUT and a JSON sidecar OUT.json "
                    "(bone.ply → bone.ply.json) with the resolved configuration, timings, counts and, "
                    "for a sweep, its pose chain, spacing, segmentation and frame registration.")
    p.add_argument("input", type=Path, help="point cloud file or tracked sweep (a cloud that sweep2points "
                                            "wrote, .ply or .npz, brings each point's probe position and "
                                            "frame along, as the sweep would)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output mesh (.ply, .obj or .stl)")
    p.add_argument("--units", default="mm", choices=list(UNITS_MM),
                   help="unit of a point cloud file's coordinates; they are converted to mm, and the "
                        "mesh is written in mm (default: mm)")
    p.add_argument("--method", default="ultraboneudf", choices=sorted(NAMES), help="method (default: ultraboneudf)")
    add_run_options(p, DEFAULT_PRESET)
    p.add_argument("--checkpoint-every", type=_at_least(1), default=None, metavar="N",
                   help="save the training's state every N steps to OUT.ckpt (removed once the mesh "
                        "is written), so that a killed run can --resume")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT.ckpt when it exists (same input, preset, --set and seed; "
                        "the same result as an uninterrupted run)")
    add_sweep_options(p)
    p.set_defaults(func=run)


def checkpoint_path(output: Path) -> Path:
    """Where ``reconstruct -o OUTPUT`` keeps its training checkpoint: ``OUTPUT.ckpt``."""
    return output.with_name(output.name + ".ckpt")


def read_input(path: Path, args: argparse.Namespace, progress: Progress
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, dict | None]:
    """Points (mm) from a cloud file, or compounded from a sweep (a folder or a sequence file); for
    a sweep, or a cloud ``sweep2points`` wrote with them, also the probe position of each point (mm,
    same frame) and its frame index; for a sweep what it gave (pose chain, spacing, shear,
    segmentation; for the sidecar). ``None`` for each the input lacks."""
    from ..io import load_points, load_sweep_columns
    from ..sweep import is_sweep_path

    if path.exists() and is_sweep_path(path):
        if args.units != "mm":
            raise InputError(f"{path}: --units applies to point cloud files; a sweep's geometry comes "
                             f"from its calibration (mm)")
        res = sweep_points(path, args, progress)
        return res.points.points, res.points.probe_position, res.points.frame_index, res.info
    given = sweep_options_given(args)
    if given:
        raise InputError(f"{path}: {', '.join(given)} {'apply' if len(given) > 1 else 'applies'} to "
                         f"tracked sweeps, not to a point cloud file")
    points = load_points(path)
    probe, frames = load_sweep_columns(path, len(points))
    scale = UNITS_MM[args.units]
    return points * scale, None if probe is None else probe * scale, frames, None


def run(args: argparse.Namespace) -> int:
    from ..checkpoints import Checkpoint
    from ..io import check_outputs, sha256_file
    from ..pipeline import configure, reconstruct
    from ..progress import Progress

    output = check_outputs(args.output, (args.input,))  # before any work: never lose the user's data
    overrides = {} if args.iters is None else {"train.iters": args.iters}
    _, entry = configure(args.preset, args.method, None, overrides, args.assignments)  # before reading
    progress = Progress(quiet=args.quiet)
    checkpoint = None
    if args.checkpoint_every is not None or args.resume:
        if not entry.takes_checkpoint:
            raise InputError(f"--method {args.method} cannot checkpoint its training; drop "
                             f"--checkpoint-every/--resume")
        checkpoint = Checkpoint(checkpoint_path(output), every=args.checkpoint_every or 0, resume=args.resume)
        if args.resume and not checkpoint.path.exists():
            progress.log(f"no checkpoint {checkpoint.path} yet: training starts at step 0")
    points, probe, frames, sweep_info = read_input(args.input, args, progress)
    rec = reconstruct(points, preset=args.preset, device=args.device, seed=args.seed, method=args.method,
                      assignments=args.assignments, progress=progress, source=str(args.input),
                      probe_positions=probe, frame_index=frames, checkpoint=checkpoint, **overrides)
    if rec.mesh is None:
        print(f"ultraboneudf reconstruct: no surface was found in {args.input}; nothing written "
              "(see the loss history with --set train.iters=… or try another preset)", file=sys.stderr)
        return 1
    rec.input.update(path=str(args.input.resolve()), sha256=sha256_file(args.input), units=args.units)
    if sweep_info is not None:
        rec.input["sweep"] = sweep_info
    elif probe is not None:  # a cloud file that carries its sweep's columns
        rec.input["sweep_columns"] = ["probe"] + ([] if frames is None else ["frame"])
    sidecar = rec.save(output)
    if checkpoint is not None:
        checkpoint.path.unlink(missing_ok=True)  # the run is complete: nothing left to resume
    t = rec.timings
    progress.log(f"wrote {output} ({rec.counts['vertices']} vertices, {rec.counts['faces']} faces) and "
                 f"{sidecar}; {t['total_s']:.1f} s (preprocess {t['preprocess_s']:.1f}, "
                 f"train {t['train_s']:.1f}, extract {t['extract_s']:.1f}) on {rec.device}")
    for warning in rec.fit_warnings(cli=True):  # shown even with --quiet: they concern the result
        print(f"ultraboneudf reconstruct: warning: {warning}", file=sys.stderr)
    return 0
