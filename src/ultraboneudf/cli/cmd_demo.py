"""``ultraboneudf demo``: built-in synthetic sweep → mesh → evaluation → picture, on the CPU."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..config import DEFAULT_PRESET
from ..errors import InputError
from . import add_overwrite
from .cmd_reconstruct import add_run_options, check_config
from .fit_hints import print_fit_issues


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="run the whole pipeline on built-in synthetic data",
        description="Simulate a tracked sweep over a synthetic open bone-like surface (slices, gaps, "
                    "noise, tracking jitter), reconstruct it, and compare the mesh with the known truth. "
                    "Writes the input points, the truth, the mesh with its sidecar, the evaluation and "
                    "a distance-coloured picture to --out, a new folder (or an earlier demo's, which "
                    "is replaced as a whole).")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default: demo_out)")
    p.add_argument("--samples", type=int, default=500_000,
                   help="area samples per surface for the Chamfer distance (default: 500,000)")
    add_run_options(p, DEFAULT_PRESET)
    add_overwrite(p, "the --out folder as a whole")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..io import check_output

    check_output(args.out, overwrite=args.overwrite, kind="folder")
    if args.samples < 1:
        raise InputError(f"--samples: must be at least 1, got {args.samples}")
    args.method = "ultraboneudf"
    overrides = {} if args.iters is None else {"train.iters": args.iters}
    check_config(args, overrides)
    return _run(args, overrides)


def _run(args: argparse.Namespace, overrides: dict) -> int:
    from ..evaluation import evaluate
    from ..io import mesh_bytes, record, save_json, sidecar_path, write_folder_output
    from ..io.outputs import sha256_bytes
    from ..pipeline import reconstruct
    from ..progress import Progress
    from ..synth import bone_phantom

    progress = Progress(quiet=args.quiet)
    out: Path = args.out
    phantom = bone_phantom(seed=args.seed)
    progress.log(f"demo: synthetic sweep of {len(phantom.points)} points over a 120 mm bone-like surface "
                 f"(slices, two frame gaps, segmentation gaps, 0.15 mm noise, 0.2 mm tracking jitter)")
    rec = reconstruct(phantom.points, preset=args.preset, device=args.device, seed=args.seed,
                      assignments=args.assignments, progress=progress, source="demo phantom", warn=False,
                      **overrides)
    if rec.mesh is None:
        progress.log("demo: the reconstruction found no surface; nothing written")
        return 1
    points = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in phantom.points).encode()
    rec.input.update({"path": str((out / "demo_points.xyz").resolve()), "sha256": sha256_bytes(points),
                      "note": "built-in demo phantom"})
    result = evaluate(rec.mesh, phantom.truth, samples=args.samples, seed=0)
    picture = _picture(rec.mesh, phantom.truth, result.cd_mm, args.preset)

    def fill(folder: Path) -> None:
        (folder / "demo_points.xyz").write_bytes(points)
        (folder / "demo_truth.ply").write_bytes(mesh_bytes(phantom.truth, folder / "demo_truth.ply"))
        mesh = mesh_bytes(rec.mesh, folder / "demo_mesh.ply")
        (folder / "demo_mesh.ply").write_bytes(mesh)
        save_json({"written_by": "ultraboneudf", **rec.sidecar(), "mesh": "demo_mesh.ply",
                   "output": "demo_mesh.ply", "sha256": sha256_bytes(mesh)}, sidecar_path(folder / "demo_mesh.ply"))
        save_json(result.to_dict(), folder / "demo_eval.json")
        (folder / "demo_mesh.png").write_bytes(picture)

    write_folder_output(out, fill, record("demo", seed=args.seed, preset=args.preset), overwrite=args.overwrite)
    t = rec.timings
    print(f"demo: Chamfer distance to the known truth {result.cd_mm:.3f} mm, HD95 {result.hd95_mm:.3f} mm "
          f"({rec.counts['faces']} faces, {t['total_s']:.1f} s on {rec.device}: preprocess "
          f"{t['preprocess_s']:.1f} s, train {t['train_s']:.1f} s, extract {t['extract_s']:.1f} s)")
    print_fit_issues(rec, "demo", sys.stdout)
    print(f"demo: wrote {out}/demo_mesh.ply, demo_mesh.ply.json, demo_eval.json, demo_mesh.png")
    return 0


def _picture(mesh, truth, cd_mm: float, preset: str) -> bytes:
    """A distance-coloured render of the reconstruction against the truth (mean written = CD), PNG."""
    from ..evaluation.render import reference_points, render_distance_image
    from ..pictures import png_bytes

    return png_bytes(render_distance_image(mesh, reference_points(truth, samples=500_000), mean_mm=cd_mm,
                                           title=f"demo: {preset} preset, colour = distance to the truth (mm)"))
