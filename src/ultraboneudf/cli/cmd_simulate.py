"""``ultraboneudf simulate BONE_MESH -o SWEEP_DIR``: a simulated tracked sweep with known truth."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..errors import InputError
from . import add_overwrite


def register(sub: argparse._SubParsersAction) -> None:
    from ..synth.simulation_config import NOISE_PRESETS, SimulationConfig

    names = ", ".join(f.name for f in dataclasses.fields(SimulationConfig))
    p = sub.add_parser(
        "simulate", help="simulate a tracked ultrasound sweep over a closed bone mesh",
        description="Move a linear probe along a closed bone mesh (mm; the sweep follows its longest "
                    "axis) and write a tracked sweep in the UltraBones100k layout: B-mode-like frames, "
                    "true and 'predicted' bone masks, poses with tracking noise and the calibration, "
                    "plus the visible ground-truth surface (gt_visible.ply) and the closed mesh "
                    "(gt_closed.ply).")
    p.add_argument("mesh", type=Path, help="closed (watertight) bone mesh in mm (.ply .obj .stl .off)")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output sweep folder: a new folder, or an earlier simulation's (replaced as a whole)")
    p.add_argument("--noise", choices=list(NOISE_PRESETS), default="default",
                   help="noise level of the path, tracking and predicted masks (default: default)")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: from --frame-spacing)")
    p.add_argument("--frame-spacing", type=float, default=None,
                   help="mean distance between frames in mm (default 0.8)")
    p.add_argument("--spacing-mm", type=float, default=None, help="pixel size in mm (default 0.15)")
    p.add_argument("--width-px", type=int, default=None, help="image width in pixels (default 256)")
    p.add_argument("--height-px", type=int, default=None, help="image height in pixels (default 320)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                   help=f"any simulator option; repeatable. Options: {names}")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_overwrite(p, "the output folder as a whole")
    p.add_argument("--force", dest="overwrite", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def parse_assignments(items: list[str]) -> dict:
    """``KEY=VALUE`` strings → simulator options of the fields' own types (the configuration's
    parser: numbers, ``a,b,c`` tuples, ``none``); :class:`InputError` for a bad item, key or value."""
    import typing

    from ..config import parse_key_values
    from ..synth.simulation_config import SimulationConfig

    return parse_key_values(items, "--set", typing.get_type_hints(SimulationConfig), what="simulator option")


MAX_FRAME_BYTES = 8 << 30
"""The frames and masks of a simulation must fit in this many bytes (they are held in memory)."""


def run(args: argparse.Namespace) -> int:
    from ..io import check_input, check_output
    from ..synth.simulation_config import config_with_noise

    out: Path = args.output
    check_output(out, inputs=(args.mesh,), overwrite=args.overwrite, kind="folder")
    overrides = parse_assignments(args.assignments)
    for key, value in (("n_frames", args.frames), ("frame_spacing_mm", args.frame_spacing),
                       ("spacing_mm", args.spacing_mm), ("width_px", args.width_px),
                       ("height_px", args.height_px)):
        if value is not None:
            overrides[key] = value
    if args.seed < 0:
        raise InputError(f"--seed must be 0 or more, got {args.seed}")
    overrides["seed"] = args.seed
    cfg = config_with_noise(args.noise, **overrides)
    check_input(args.mesh, "mesh file")
    from ..synth.simulator import load_bone_mesh

    mesh = load_bone_mesh(args.mesh)
    frames = cfg.n_frames or int(float(mesh.extents.max()) / cfg.frame_spacing_mm) + 1
    size = frames * cfg.width_px * cfg.height_px * 4  # frames, two mask sets, the truth's pass
    if size > MAX_FRAME_BYTES:
        raise InputError(f"about {frames:,} frames of {cfg.width_px}x{cfg.height_px} px would hold "
                         f"{size / 2**30:.1f} GiB, more than {MAX_FRAME_BYTES >> 30} GiB; fewer or smaller "
                         f"frames (--frames, --frame-spacing, --width-px, --height-px)")
    return _run(args, cfg, mesh)


def _run(args: argparse.Namespace, cfg, mesh) -> int:
    from ..io import record, sha256_file, write_folder_output
    from ..progress import Progress
    from ..synth.simulator import simulate_sweep, write_simulation

    progress = Progress(quiet=args.quiet)
    sim = simulate_sweep(mesh, cfg, progress=progress)
    meta = record("simulate", mesh={"path": str(args.mesh.resolve()), "sha256": sha256_file(args.mesh)},
                  noise=args.noise, seed=args.seed)
    write_folder_output(args.output, lambda folder: write_simulation(sim, folder), meta, overwrite=args.overwrite)
    info = sim.info
    print(f"simulate: {info['frames']} frames over {info['sweep_length_mm']:.1f} mm of {args.mesh.name} "
          f"(noise {args.noise}, seed {args.seed}); visible surface {info['visible_area_mm2']:.0f} mm²; "
          f"wrote {args.output}")
    return 0
