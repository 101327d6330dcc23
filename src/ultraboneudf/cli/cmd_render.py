"""``ultraboneudf render MESH [MESH …] -o OUT.png|OUT.html``: distance-coloured pictures."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from . import add_overwrite
from .cmd_evaluate import GT_POSE_HELP, placed_ground_truth, warn_misplaced


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render", help="distance-coloured picture (PNG) or interactive viewer (HTML) of a reconstruction",
        description="Colour = distance (mm) from the reconstruction to the ground truth, clamped to "
                    "0–VMAX, with a colour bar and the mean distance under it (as the paper's Figs. 7–9). "
                    "One MESH and OUT.png: several views side by side; several MESHes: a grid of methods "
                    "(columns) × views (rows). OUT.html: a self-contained WebGL viewer (one MESH) with "
                    "toggles for the ground truth and the input points. Without --gt the mesh is grey.")
    p.add_argument("meshes", nargs="+", metavar="MESH", help="reconstructed mesh(es) in mm")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="OUT.png or OUT.html")
    p.add_argument("--gt", metavar="GT", help="ground-truth mesh in mm (colours are distances to it)")
    p.add_argument("--gt-pose", metavar="T", help=GT_POSE_HELP)
    p.add_argument("--points", metavar="RAW", help="raw ultrasound cloud in mm: pseudo ground truth for the "
                   "colours (as evaluate) and the input points of the viewer")
    p.add_argument("--pseudo-gt-mm", type=float, default=None, metavar="T",
                   help="pseudo-GT threshold τ in mm (default 2 when --points is given)")
    p.add_argument("--labels", metavar="A,B,…", help="column titles of a grid (default: file names)")
    p.add_argument("--views", default=None, metavar="V,…",
                   help="views: front,right,back,left,top,bottom or AZ:EL in degrees "
                        "(default front,right,back; grid: front,back)")
    p.add_argument("--vmax", type=float, default=5.0, metavar="MM", help="top of the colour scale (default 5 mm)")
    p.add_argument("--tile-height", type=int, default=None, metavar="PX",
                   help="height of one view in pixels (default 480; grid 360)")
    p.add_argument("--colour-samples", type=int, default=1_000_000, metavar="N",
                   help="ground-truth points sampled to colour by (default 1,000,000)")
    p.add_argument("--show-gt", action="store_true", help="grid: add a grey ground-truth column")
    p.add_argument("--title", default=None, help="title (PNG of one mesh, HTML)")
    p.add_argument("--seed", type=int, default=0, help="seed of the ground-truth sampling (default 0)")
    add_overwrite(p, "OUT and its sidecar OUT.json")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..io import check_input, check_output, load_points, read_mesh, record, sha256_file, write_output

    out = Path(args.out)
    kind = out.suffix.lower()
    if kind not in (".png", ".html", ".htm"):
        raise InputError(f"{out}: unknown output type {out.suffix!r}; use .png or .html")
    if kind != ".png" and len(args.meshes) > 1:
        raise InputError(f"{out}: the HTML viewer shows one mesh; give one MESH or write a .png grid")
    if not args.vmax > 0:
        raise InputError(f"--vmax: must be > 0 mm, got {args.vmax}")
    if args.pseudo_gt_mm is not None and not args.points:
        raise InputError("--pseudo-gt-mm needs --points (the raw ultrasound cloud)")
    if args.gt_pose and not args.gt:
        raise InputError("--gt-pose places the ground truth and needs --gt")
    if args.pseudo_gt_mm is not None and not args.pseudo_gt_mm >= 0:
        raise InputError(f"--pseudo-gt-mm: must be ≥ 0 mm, got {args.pseudo_gt_mm}")
    if args.colour_samples < 1:
        raise InputError(f"--colour-samples: must be at least 1, got {args.colour_samples}")
    if args.tile_height is not None and not 16 <= args.tile_height <= 8192:
        raise InputError(f"--tile-height: between 16 and 8192 pixels, got {args.tile_height}")
    labels = [s.strip() for s in args.labels.split(",")] if args.labels else [Path(m).stem for m in args.meshes]
    if len(labels) != len(args.meshes):
        raise InputError(f"--labels: {len(labels)} labels for {len(args.meshes)} meshes")
    if args.points and not args.gt and kind == ".png":
        raise InputError("--points colours by the pseudo ground truth and needs --gt")
    inputs = [*args.meshes, *(p for p in (args.gt, args.points, args.gt_pose) if p)]
    check_output(out, inputs=inputs, overwrite=args.overwrite)
    for given in inputs:
        check_input(given, "file")
    from ..evaluation.render import parse_view

    views = [parse_view(v) for v in args.views.split(",")] if args.views else None
    meshes = [read_mesh(m) for m in args.meshes]
    gt = read_mesh(args.gt) if args.gt else None
    if args.gt and gt is None:
        raise InputError(f"{args.gt}: holds no triangles")
    if args.gt_pose:
        gt = placed_ground_truth(gt, args.gt_pose)
    raw = load_points(args.points) if args.points else None
    if kind == ".png" and len(meshes) == 1 and meshes[0] is None:
        raise InputError(f"{args.meshes[0]}: holds no triangles; nothing to render")
    if kind != ".png" and meshes[0] is None:
        raise InputError(f"{args.meshes[0]}: holds no triangles; nothing to show")
    if gt is not None:
        warn_misplaced("render", args.gt, gt, list(zip(args.meshes, meshes)), args.points, raw)
    data = _draw(args, kind, meshes, labels, views, gt, raw)
    meta = record("render", inputs={str(p): sha256_file(p) for p in inputs},
                  options={k: str(v) for k, v in sorted(vars(args).items()) if k not in ("func", "out")})
    write_output(out, data, meta, overwrite=args.overwrite)
    print(out)
    return 0


def _draw(args, kind, meshes, labels, views, gt, raw) -> bytes:
    """The picture's (PNG) or the viewer's (HTML) bytes."""
    from ..evaluation.render import reference_points, render_distance_image, render_grid_image
    from ..pictures import png_bytes
    from ..evaluation.viewer import viewer_html

    reference = None
    if gt is not None:
        reference = reference_points(gt, raw, args.pseudo_gt_mm, args.colour_samples, args.seed)
    kwargs = {"vmax": args.vmax, **({"views": views} if views else {}),
              **({"tile_height": args.tile_height} if args.tile_height else {})}
    if kind == ".png" and len(meshes) == 1:
        return png_bytes(render_distance_image(meshes[0], reference, title=args.title, **kwargs))
    if kind == ".png":
        return png_bytes(render_grid_image(dict(zip(labels, meshes)), reference,
                                           ground_truth=gt if args.show_gt else None, **kwargs))
    return viewer_html(meshes[0], reference=reference, ground_truth=gt, points=raw,
                       title=args.title or labels[0], vmax=args.vmax).encode("utf-8")
