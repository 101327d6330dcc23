"""``ultraboneudf evaluate RECON --gt GT``: Chamfer distance and HD95 in mm (docs/ALGORITHMS.md §6.2)."""

from __future__ import annotations

import argparse
import sys

from ..errors import InputError
from . import add_overwrite

GT_POSE_HELP = ("a rigid 4×4 transform (mm) that places GT in the frame of what it is compared with, "
                "applied before scoring: the T.json of `ultraboneudf register GT SCAN` (registered to the "
                "ultrasound points, not to the mesh being scored), or a matrix or landmark file as "
                "`register --init` reads")


def placed_ground_truth(gt, pose_path: str):
    """``gt`` (a trimesh) moved by the pose in ``pose_path`` (a new mesh; the file is not touched)."""
    from ..registration.initial import read_init

    matrix, _ = read_init(pose_path)
    placed = gt.copy()
    placed.apply_transform(matrix)
    return placed


def warn_misplaced(command: str, gt_path: str, gt, meshes: list, points_path: str | None, raw) -> None:
    """One stderr line (also with ``--quiet``) for each of ``meshes`` (``(path, trimesh or None)``)
    and the points ``raw`` that lie in another frame or unit than ``gt``
    (:func:`~ultraboneudf.evaluation.placement.placement_warnings`)."""
    from ..evaluation.placement import placement_warnings

    scored = [(str(path), mesh.vertices) for path, mesh in meshes if mesh is not None]
    if raw is not None:
        scored.append((str(points_path), raw))
    for warning in placement_warnings((str(gt_path), gt.vertices), scored):
        print(f"ultraboneudf {command}: warning: {warning}", file=sys.stderr)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate", help="Chamfer distance and HD95 (mm) of a reconstruction against a ground-truth mesh",
        description="Metrics of docs/ALGORITHMS.md §6.2, in mm: points sampled uniformly by area on both "
                    "meshes (seeded), directed Euclidean nearest-neighbour distances, CD = ½(mean d_RG + "
                    "mean d_GR), HD95 = max of the two directed 95th percentiles. With --points, the "
                    "ground truth is restricted to samples within --pseudo-gt-mm of the raw ultrasound "
                    "cloud (pseudo ground truth). A reconstruction without triangles is reported as a "
                    "failure (null metrics), never as zero.")
    p.add_argument("recon", metavar="RECON", help="reconstructed mesh in mm (.ply .obj .stl .off)")
    p.add_argument("--gt", required=True, metavar="GT", help="ground-truth mesh in mm")
    p.add_argument("--gt-pose", metavar="T", help=GT_POSE_HELP)
    p.add_argument("--points", metavar="RAW",
                   help="raw (not down-sampled) ultrasound point cloud in mm; enables the pseudo ground truth")
    p.add_argument("--pseudo-gt-mm", type=float, default=None, metavar="T",
                   help="pseudo-GT threshold τ in mm (default 2, as the paper; the official code uses 1); "
                        "needs --points")
    p.add_argument("--within-mm", type=float, default=None, metavar="T",
                   help="also the shares within T mm, as real data is scored against CT: of the "
                        "reconstruction's area near the whole ground-truth mesh (on_gt; what it invented "
                        "lies farther) and of the (pseudo) ground truth near the reconstruction (covered; "
                        "what it missed lies farther); --json then adds within_mm, on_gt and covered")
    p.add_argument("--samples", type=int, default=5_000_000, metavar="N",
                   help="points sampled on each surface (default 5,000,000 as the reference code)")
    p.add_argument("--seed", type=int, default=0, help="seed of the surface sampling (default 0)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"],
                   help="nearest-neighbour search: cpu (multi-threaded KD-tree, default), cuda (GPU grid), auto")
    p.add_argument("--json", metavar="OUT", help="write the metrics as JSON with the keys cd_mm, hd95_mm, "
                   "d_rg_mean_mm, d_gr_mean_mm, hd95_rg_mm, hd95_gr_mm, samples, pseudo_gt_mm (and "
                   "beside it the sidecar OUT.json: which meshes, samples and seed)")
    add_overwrite(p, "OUT and its sidecar")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json
    import math

    from ..io import check_input, check_output, load_mesh, load_points, read_mesh, record, sha256_file, write_output

    if args.samples < 1:
        raise InputError(f"--samples: must be at least 1, got {args.samples}")
    if args.pseudo_gt_mm is not None and not args.points:
        raise InputError("--pseudo-gt-mm needs --points (the raw ultrasound cloud to filter by)")
    if args.pseudo_gt_mm is not None and not args.pseudo_gt_mm >= 0:
        raise InputError(f"--pseudo-gt-mm: must be ≥ 0 mm, got {args.pseudo_gt_mm}")
    if args.within_mm is not None and not (math.isfinite(args.within_mm) and args.within_mm >= 0):
        raise InputError(f"--within-mm: must be a finite number ≥ 0 mm, got {args.within_mm}")
    inputs = [p for p in (args.recon, args.gt, args.points, args.gt_pose) if p]
    if args.json:
        check_output(args.json, inputs=inputs, overwrite=args.overwrite)
    for given in inputs:
        check_input(given, "file")
    recon = read_mesh(args.recon)
    gt = load_mesh(args.gt)
    if args.gt_pose:
        gt = placed_ground_truth(gt, args.gt_pose)
    raw = load_points(args.points) if args.points else None
    from ..evaluation.metrics import evaluate
    from ..extraction.quality import mesh_quality
    from ..progress import Progress

    warn_misplaced("evaluate", args.gt, gt, [(args.recon, recon)], args.points, raw)
    progress = Progress(quiet=args.quiet)
    result = evaluate(recon, gt, raw_points=raw, pseudo_gt_mm=args.pseudo_gt_mm, samples=args.samples,
                      seed=args.seed, device=args.device, progress=progress, gt_source=str(args.gt),
                      within_mm=args.within_mm)
    if args.json:
        meta = record("evaluate", inputs={str(p): sha256_file(p) for p in inputs}, samples=args.samples,
                      seed=args.seed, pseudo_gt_mm=result.pseudo_gt_mm, within_mm=args.within_mm)
        write_output(args.json, (json.dumps(result.to_json(), indent=2) + "\n").encode("utf-8"), meta,
                     overwrite=args.overwrite)
    tau = "whole ground truth" if result.pseudo_gt_mm is None else f"pseudo-GT τ = {result.pseudo_gt_mm:g} mm"
    if result.failed:
        print(f"ultraboneudf evaluate: {args.recon}: {result.reason}: counted as a failure (no metrics)",
              file=sys.stderr)
        print(f"failed: {result.reason} ({tau})")
        return 0
    print(f"CD    {result.cd_mm:.4f} mm    HD95  {result.hd95_mm:.4f} mm")
    print(f"d_RG  mean {result.d_rg_mean_mm:.4f} mm, P95 {result.hd95_rg_mm:.4f} mm")
    print(f"d_GR  mean {result.d_gr_mean_mm:.4f} mm, P95 {result.hd95_gr_mm:.4f} mm")
    print(f"HD95 alternatives: P95 of pooled distances {result.hd95_union_mm:.4f} mm, "
          f"mean of directed P95 {result.hd95_mean_mm:.4f} mm")
    if result.within_mm is not None:
        scored = "the whole ground truth" if result.pseudo_gt_mm is None else "the pseudo ground truth"
        print(f"within {result.within_mm:g} mm: {result.on_gt:.3f} of the mesh area near the ground-truth mesh "
              f"(on_gt), {result.covered:.3f} of {scored} near the mesh (covered)")
    print(f"samples {result.samples:,} per surface, {result.samples_gt:,} ground-truth samples kept "
          f"({tau}), seed {result.seed}, {result.timings.get('total_s', 0.0):.1f} s on {result.device}")
    q = mesh_quality(recon)
    print(f"mesh  area {q['area']:.1f} mm² ({q['area'] / gt.area:.3f}× the ground-truth mesh), "
          f"{q['components']} components, {q['boundary_edges']} boundary edges ({q['boundary_loops']} loops), "
          f"{q['nonmanifold_edges']} non-manifold edges, {q['duplicate_faces']} duplicate faces")
    return 0
