"""``ultraboneudf register CT_MESH TARGET -o T.json``: the rigid pose of a CT bone in the ultrasound's
frame, from any start."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..config import DEFAULT_PRESET, PRESETS, UNITS_MM
from ..errors import InputError
from ..io.outputs import check_output
from . import add_overwrite
from .sweep_input import add_sweep_options, sweep_options_given

LOW_CONFIDENCE = 0.1
"""Below this confidence the command warns that another pose explains the ultrasound nearly as well."""
LOW_OVERLAP = 0.3
"""Below this overlap the command warns that the CT explains little of the ultrasound."""
LOW_SENSITIVITY = 0.1
"""Below this sensitivity the command warns of a motion the ultrasound barely constrains."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "register", help="rigid pose of a CT bone in the ultrasound's frame (no initial pose needed)",
        description="Find the rigid transform that places the CT bone (a mesh in mm) on the ultrasound "
                    "surface: TARGET is a reconstructed mesh, a point cloud file (mm) or a tracked sweep "
                    "(reconstructed first with the default preset, or registered to its points with "
                    "--no-reconstruct). No initial pose is needed: poses are searched globally, then "
                    "refined by trimmed point-to-plane ICP that ignores what the CT cannot explain "
                    "(false echoes). Writes T.json: the 4×4 transform CT → target (mm), the residual on "
                    "the explained points, the share of the ultrasound the CT explains (overlap), the "
                    "share of the CT the ultrasound saw (coverage), the confidence (gap to the best "
                    "other pose), the least-constrained motion, timings, and the inputs' paths and "
                    "SHA-256 with every option and the seed, to repeat it. See docs/registration.md.")
    p.add_argument("ct", type=Path, metavar="CT_MESH", help="CT bone surface in mm (.ply .obj .stl .off)")
    p.add_argument("target", type=Path, metavar="TARGET",
                   help="ultrasound surface: a mesh file, a point cloud file or a tracked sweep")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="T.json", help="the registration (JSON)")
    p.add_argument("--init", type=Path, default=None, metavar="FILE",
                   help="start from this pose instead of searching: a 4×4 CT → target (JSON list, "
                        "{\"transform\": …} such as an earlier T.json, 16 numbers in a text file, .npy) or "
                        "landmark pairs (JSON {\"ct\": [[x,y,z]…], \"target\": […]}, or text rows "
                        "'x y z X Y Z'; at least 3, mm)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--set", dest="assignments", action="append", default=[], metavar="KEY=VALUE",
                   help="registration option, e.g. --set inlier_mm=1.5 or --set anchors=10 (repeatable; "
                        "see docs/registration.md)")
    p.add_argument("--png", type=Path, default=None, metavar="OUT.png",
                   help="also draw the CT in place, coloured by distance to the ultrasound")
    p.add_argument("--html", type=Path, default=None, metavar="OUT.html",
                   help="also write an interactive viewer of the CT in place with the ultrasound points")
    p.add_argument("--units", default="mm", choices=list(UNITS_MM),
                   help="unit of a point cloud TARGET's coordinates (default: mm)")
    p.add_argument("--threads", type=int, default=-1,
                   help="threads of the nearest-neighbour searches (default: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_overwrite(p, "T.json, the pictures and --mesh")
    g = p.add_argument_group("a tracked sweep as TARGET")
    g.add_argument("--no-reconstruct", action="store_true",
                   help="register to the sweep's compounded points instead of its reconstruction")
    g.add_argument("--preset", default=DEFAULT_PRESET, choices=list(PRESETS),
                   help=f"reconstruction preset (default: {DEFAULT_PRESET})")
    g.add_argument("--device", default="auto", help="reconstruction device: auto, cpu, cuda (default: auto)")
    g.add_argument("--iters", type=int, default=None, help="reconstruction training iterations")
    g.add_argument("--mesh", type=Path, default=None, metavar="OUT.ply",
                   help="keep the sweep's reconstruction (with its sidecar)")
    add_sweep_options(p)
    p.set_defaults(func=run)


def _check_figure(path: Path | None, suffixes: tuple[str, ...], option: str, inputs: tuple[Path, ...],
                  taken: list[Path], overwrite: bool) -> None:
    if path is None:
        return
    if path.suffix.lower() not in suffixes:
        raise InputError(f"{path}: {option} writes {' or '.join(suffixes)}")
    if any(path.resolve() == t.resolve() for t in taken):
        raise InputError(f"{path}: named for two outputs")
    check_output(path, inputs=inputs, overwrite=overwrite)
    taken.append(path)


def _read_target(args: argparse.Namespace, progress) -> tuple[Any, dict[str, Any]]:
    """The registration's target (points or a mesh) and the JSON's record of it."""
    from ..io import sha256_file
    from ..registration.solve import mesh_file
    from ..sweep import is_sweep_path
    from ..sweep.front_end import sweep_points
    from .cmd_reconstruct import read_points
    from .sweep_input import sweep_options

    path: Path = args.target
    record: dict[str, Any] = {"path": str(path.resolve()) if path.exists() else str(path)}
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    sweep = is_sweep_path(path)
    if not sweep:
        given = sweep_options_given(args) + [f"--{o}" for o in ("no-reconstruct", "mesh")
                                             if getattr(args, o.replace("-", "_"))]
        if given:
            raise InputError(f"{path}: {', '.join(given)} {'apply' if len(given) > 1 else 'applies'} to a tracked "
                             f"sweep, not to a file")
        mesh = mesh_file(path)
        if mesh is not None:
            if args.units != "mm":
                raise InputError(f"{path}: --units applies to point cloud files; a mesh is read in mm")
            record.update(kind="mesh", sha256=sha256_file(path))
            return mesh, record
    if sweep:
        if args.units != "mm":
            raise InputError(f"{path}: --units applies to point cloud files; a sweep's geometry comes "
                             f"from its calibration (mm)")
        res = sweep_points(path, sweep_options(args), progress)
        points, probe, frames, sweep_info = res.points, res.probe_position, res.frame_index, res.info
    else:
        (points, probe, frames), sweep_info = read_points(path, args), None
    record.update(sha256=sha256_file(path), units=args.units)
    if not sweep:
        record["kind"] = "points"
        return points, record
    record["sweep"] = sweep_info
    if args.no_reconstruct:
        record["kind"] = "sweep points"
        return points, record
    from ..pipeline import reconstruct

    overrides = {} if args.iters is None else {"train.iters": args.iters}
    rec = reconstruct(points, preset=args.preset, device=args.device, seed=args.seed, progress=progress,
                      source=str(path), probe_positions=probe, frame_index=frames, warn=False, **overrides)
    if rec.mesh is None:
        raise InputError(f"{path}: the reconstruction found no surface; register to its points with "
                         f"--no-reconstruct, or reconstruct it yourself and pass the mesh")
    rec.input.update(path=record["path"], sha256=record["sha256"], sweep=sweep_info)
    side = rec.sidecar()
    if args.mesh is not None:
        from ..io import save_mesh_with_sidecar

        save_mesh_with_sidecar(rec.mesh, args.mesh, side, overwrite=args.overwrite)
    record.update(kind="sweep reconstruction", reconstruction={
        k: side[k] for k in ("method", "preset", "config", "seed", "device", "version", "counts", "timings")})
    if args.mesh is not None:
        record["reconstruction"]["mesh"] = str(args.mesh.resolve())
    return rec.mesh, record


def run(args: argparse.Namespace) -> int:
    from ..io import check_outputs, load_mesh, sha256_file
    from ..io.outputs import record as output_record, write_outputs
    from ..progress import Progress
    from ..registration import read_init
    from ..registration.options import RegisterOptions, with_overrides
    from ..registration.solve import register as solve

    inputs = tuple(p for p in (args.ct, args.target, args.init) if p is not None)
    if args.output.suffix.lower() != ".json":
        raise InputError(f"{args.output}: the output must be a .json file")
    output = check_output(args.output, inputs=inputs, overwrite=args.overwrite)      # before any work
    taken = [output]
    _check_figure(args.png, (".png",), "--png", inputs, taken, args.overwrite)
    _check_figure(args.html, (".html", ".htm"), "--html", inputs, taken, args.overwrite)
    if args.mesh is not None:
        check_outputs(args.mesh, inputs, overwrite=args.overwrite)
    if args.threads == 0 or args.threads < -1:
        raise InputError(f"--threads: a positive number or -1 (all cores), got {args.threads}")
    values = {}
    for item in args.assignments:
        key, sep, value = item.partition("=")
        if not sep:
            raise InputError(f"--set {item!r}: expected KEY=VALUE")
        values[key.strip()] = value.strip()
    options = with_overrides(RegisterOptions(), values)
    progress = Progress(quiet=args.quiet)
    ct = load_mesh(args.ct)
    init, init_record = (None, None)
    if args.init is not None:
        init, init_record = read_init(args.init)
        init_record.update(path=str(args.init.resolve()), sha256=sha256_file(args.init))
    target, target_record = _read_target(args, progress)
    reg = solve(ct, target, init=init, seed=args.seed, options=options, progress=progress, workers=args.threads)
    reg.input = {"ct": {"path": str(args.ct.resolve()), "sha256": sha256_file(args.ct)}, "target": target_record,
                 **({"init": init_record} if init_record else {})}
    figures = []
    if args.png is not None or args.html is not None:
        from ..registration.figures import registration_html, registration_png
        from ..registration.solve import as_target_points

        points = as_target_points(target, args.seed)[0]
        if args.png is not None:
            figures.append((args.png, registration_png(ct, reg, points)))
        if args.html is not None:
            figures.append((args.html, registration_html(ct, reg, points)))
    t = reg.to_json()
    meta = output_record("register", inputs={str(p): sha256_file(p) for p in inputs if p.is_file()})
    write_outputs([(output, (json.dumps(t, indent=2) + "\n").encode("utf-8"), meta),
                   *[(path, data, meta) for path, data in figures]], overwrite=args.overwrite)
    conf = "none (given --init)" if reg.confidence is None else f"{reg.confidence:.2f}"
    progress.log(f"wrote {output}" + "".join(f", {p}" for p, _ in figures))
    print(f"register: rotation {t['rotation_deg']:.2f}°, translation {t['translation_mm']} mm (CT → target); "
          f"residual {reg.residual_mm:.2f} mm on {100 * reg.overlap:.0f}% of the ultrasound (within "
          f"{reg.inlier_mm:g} mm); {100 * reg.coverage:.0f}% of the CT seen; confidence {conf}; "
          f"{reg.timings['total_s']:.1f} s")
    for warning in warnings_of(reg):  # shown even with --quiet: they concern the result
        print(f"ultraboneudf register: warning: {warning}", file=sys.stderr)
    return 0


def warnings_of(reg) -> list[str]:
    """Sentences on a registration the user should not trust blindly."""
    out = []
    if reg.overlap < LOW_OVERLAP:
        out.append(f"the CT explains only {100 * reg.overlap:.0f}% of the ultrasound points; check that it is "
                   f"the scanned bone (and side) and that both are in mm")
    if reg.confidence is not None and reg.confidence < LOW_CONFIDENCE and reg.runner_up is not None:
        out.append(f"another pose {reg.runner_up['distance_mm']:.1f} mm away explains the ultrasound nearly as "
                   f"well (confidence {reg.confidence:.2f}); the view may not fix the pose — scan more of the bone")
    weakest = reg.weakest_motion
    if weakest["sensitivity"] < LOW_SENSITIVITY:
        out.append(f"the ultrasound barely constrains one motion of the CT (sensitivity "
                   f"{weakest['sensitivity']:.2f}: a shift along {weakest['translation_mm']} with a turn of "
                   f"{weakest['rotation_deg']:.2f}° per mm); scan the bone's ends or other features")
    return out
