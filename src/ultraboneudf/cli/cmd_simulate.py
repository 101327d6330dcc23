"""``ultraboneudf simulate BONE_MESH -o SWEEP_DIR``: a simulated tracked sweep with known truth."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    from ..synth.sweep_config import NOISE_PRESETS, SimulationConfig

    names = ", ".join(f.name for f in dataclasses.fields(SimulationConfig))
    p = sub.add_parser(
        "simulate", help="simulate a tracked ultrasound sweep over a closed bone mesh",
        description="Move a linear probe along a closed bone mesh (mm; the sweep follows its longest "
                    "axis) and write a tracked sweep in the UltraBones100k layout: B-mode-like frames, "
                    "true and 'predicted' bone masks, poses with tracking noise and the calibration, "
                    "plus the visible ground-truth surface (gt_visible.ply) and the closed mesh "
                    "(gt_closed.ply).")
    p.add_argument("mesh", type=Path, help="closed (watertight) bone mesh in mm (.ply .obj .stl .off)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output sweep folder")
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
    p.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def parse_assignments(items: list[str]) -> dict:
    """``KEY=VALUE`` strings → simulator options of the fields' own types (the configuration's
    coercion: numbers, ``a,b,c`` tuples, ``none``); :class:`InputError` for a bad item, key or value."""
    import typing

    from ..config import coerce
    from ..synth.sweep_config import SimulationConfig

    hints = typing.get_type_hints(SimulationConfig)
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep:
            raise InputError(f"--set {item!r}: expected KEY=VALUE")
        if key not in hints:
            raise InputError(f"--set {item!r}: unknown simulator option {key!r}; options: {', '.join(hints)}")
        out[key] = coerce(hints[key], value.strip(), key)
    return out


def run(args: argparse.Namespace) -> int:
    from ..progress import Progress
    from ..synth.simulator import config_with_noise, load_bone_mesh, simulate_sweep

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        raise InputError(f"{out}: folder exists and is not empty (use --force to write into it)")
    overrides = parse_assignments(args.assignments)
    for key, value in (("n_frames", args.frames), ("frame_spacing_mm", args.frame_spacing),
                       ("spacing_mm", args.spacing_mm), ("width_px", args.width_px),
                       ("height_px", args.height_px)):
        if value is not None:
            if value <= 0:
                raise InputError(f"{key} must be positive, got {value}")
            overrides[key] = value
    overrides["seed"] = args.seed
    cfg = config_with_noise(args.noise, **overrides)
    mesh = load_bone_mesh(args.mesh)
    progress = Progress(quiet=args.quiet)
    sim = simulate_sweep(mesh, cfg, progress=progress)
    sim.write(out)
    info = sim.info
    print(f"simulate: {info['frames']} frames over {info['sweep_length_mm']:.1f} mm of {args.mesh.name} "
          f"(noise {args.noise}, seed {args.seed}); visible surface {info['visible_area_mm2']:.0f} mm²; "
          f"wrote {out}")
    return 0
