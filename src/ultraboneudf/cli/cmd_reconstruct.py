"""``ultraboneudf reconstruct INPUT -o OUT.ply``: a point cloud file (mm) or a sweep → mesh + sidecar."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..config import DEFAULT_PRESET, PRESET_HELP, PRESETS, UNITS_MM
from ..errors import InputError
from ..methods import NAMES
from . import add_overwrite
from .fit_hints import print_fit_issues
from .sweep_input import (add_sweep_options, check_sweep_options, read_options, sweep_inputs, sweep_options,
                          sweep_options_given)

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
    add_overwrite(p, "OUT, its sidecar and OUT.ckpt")
    add_sweep_options(p)
    p.set_defaults(func=run)


def checkpoint_path(output: Path) -> Path:
    """Where ``reconstruct -o OUTPUT`` keeps its training checkpoint: ``OUTPUT.ckpt``."""
    return output.with_name(output.name + ".ckpt")


def check_config(args: argparse.Namespace, overrides: dict) -> dict:
    """The ``--set`` values checked before PyTorch loads: every key, type and choice; for the
    default method (whose configuration is the preset's) every range too. The other methods'
    ranges are checked once their defaults are known (:func:`~ultraboneudf.pipeline.configure`).
    Returns the configuration so far as a dict (the preset with the user's values)."""
    from ..config import apply_overrides, preset, validate

    cfg = apply_overrides(preset(args.preset), overrides, args.assignments)
    if args.method == "ultraboneudf":
        validate(cfg)
    return cfg.to_dict()


def read_points(path: Path, args: argparse.Namespace
                ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Points (mm) of a cloud file and, from a cloud ``sweep2points`` wrote, the probe position of
    each point (mm, same frame) and its frame index (``None`` where the file has none); refused
    (:class:`InputError`) when the coordinates cannot be millimetres."""
    from ..io import check_units, load_points, load_sweep_columns

    given = sweep_options_given(args)
    if given:
        raise InputError(f"{path}: {', '.join(given)} {'apply' if len(given) > 1 else 'applies'} to "
                         f"tracked sweeps, not to a point cloud file")
    points = load_points(path)
    probe, frames = load_sweep_columns(path, len(points))
    scale = UNITS_MM[args.units]
    points = points * scale
    check_units(points, str(path))
    return points, None if probe is None else probe * scale, frames


def run(args: argparse.Namespace) -> int:
    from .. import checkpoints
    from ..io import check_input, check_output, check_outputs, sha256_file

    # every check first, none of them needs PyTorch: outputs, options, the input, the checkpoint
    inputs = (args.input, *sweep_inputs(args))
    output = check_outputs(args.output, inputs, overwrite=args.overwrite)
    checkpointing = args.checkpoint_every is not None or args.resume
    if checkpointing:
        ckpt = checkpoint_path(output)
        if ckpt.is_dir():
            raise InputError(f"{ckpt}: is a folder; the training checkpoint needs that name (move it, "
                             f"or choose another output name)")
        check_output(ckpt, inputs=inputs, kind="bare")  # its name and place; its owner below
    check_input(args.input, "file", folder=True)
    overrides = {} if args.iters is None else {"train.iters": args.iters}
    config = check_config(args, overrides)
    if args.input.is_dir() or args.input.suffix.lower() in SWEEP_SUFFIXES:
        if args.units != "mm":
            raise InputError(f"{args.input}: --units applies to point cloud files; a sweep's geometry comes "
                             f"from its calibration (mm)")
        read_options(args, args.input)
        check_sweep_options(args.input, args)
        cloud = None
    else:
        cloud = read_points(args.input, args)
    input_sha = sha256_file(args.input)
    checkpoint = None
    if checkpointing:
        key = checkpoints.run_key(input_sha, config, args.method, args.seed, preset=args.preset, units=args.units,
                                  sweep={k: str(v) for k, v in sorted(vars(args).items()) if k in _SWEEP_KEYS})
        checkpoint = checkpoints.Checkpoint(checkpoint_path(output), every=args.checkpoint_every or 0,
                                            resume=args.resume, run=key)
        checkpoints.check(checkpoint, overwrite=args.overwrite)
    return _run(args, output, overrides, cloud, checkpoint, input_sha)


def _run(args: argparse.Namespace, output: Path, overrides: dict, cloud, checkpoint, input_sha: str) -> int:
    from ..io import save_mesh_with_sidecar
    from ..pipeline import configure, reconstruct
    from ..progress import Progress

    # the run's configuration, resolved once (the method's defaults, then --iters and --set)
    config = configure(args.preset, args.method, overrides, args.assignments, checkpoint=checkpoint is not None)
    progress = Progress(quiet=args.quiet)
    if checkpoint is not None and args.resume and not checkpoint.path.exists():
        progress.log(f"no checkpoint {checkpoint.path} yet: training starts at step 0")
    if cloud is None:
        from ..sweep.front_end import sweep_points

        res = sweep_points(args.input, sweep_options(args), progress)
        points, probe, frames, sweep_info = res.points, res.probe_position, res.frame_index, res.info
    else:
        (points, probe, frames), sweep_info = cloud, None
    rec = reconstruct(points, preset=args.preset, device=args.device, seed=args.seed, method=args.method,
                      config=config, progress=progress, source=str(args.input), probe_positions=probe,
                      frame_index=frames, checkpoint=checkpoint, warn=False)
    if rec.mesh is None:
        print(f"ultraboneudf reconstruct: no surface was found in {args.input}; nothing written "
              "(see the loss history with --set train.iters=… or try another preset)", file=sys.stderr)
        return 1
    rec.input.update(path=str(args.input.resolve()), sha256=input_sha, units=args.units)
    if sweep_info is not None:
        rec.input["sweep"] = sweep_info
    elif probe is not None:  # a cloud file that carries its sweep's columns
        rec.input["sweep_columns"] = ["probe"] + ([] if frames is None else ["frame"])
    # the mesh, its sidecar and the end of the checkpoint, as a unit
    sidecar = save_mesh_with_sidecar(rec.mesh, output, rec.sidecar(), overwrite=args.overwrite,
                                     remove=[checkpoint.path] if checkpoint is not None else [])
    t = rec.timings
    progress.log(f"wrote {output} ({rec.counts['vertices']} vertices, {rec.counts['faces']} faces) and "
                 f"{sidecar}; {t['total_s']:.1f} s (preprocess {t['preprocess_s']:.1f}, "
                 f"train {t['train_s']:.1f}, extract {t['extract_s']:.1f}) on {rec.device}")
    print_fit_issues(rec, "ultraboneudf reconstruct")
    return 0


SWEEP_SUFFIXES = (".mha", ".mhd", ".nrrd", ".nhdr")
"""Sequence files read as a sweep (as :func:`~ultraboneudf.sweep.is_sweep_path` tells; a folder is one too)."""

_SWEEP_KEYS = ("calibration", "transform", "reference", "image_frame", "transforms", "segment", "masks",
               "mask_dir", "detector", "no_consistency", "threshold", "no_align_frames")
"""The options that change the points a sweep gives (part of a checkpoint's run key)."""
