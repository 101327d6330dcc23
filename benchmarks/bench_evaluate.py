"""Speed and memory of one evaluation (docs/ALGORITHMS.md §6.2) at the reference code's 5,000,000
samples per surface, and the example picture of docs/evaluation.md.

    .venv/bin/python benchmarks/bench_evaluate.py                       # 5e6 × 5e6 on the CPU
    .venv/bin/python benchmarks/bench_evaluate.py --device cuda
    .venv/bin/python benchmarks/bench_evaluate.py --scenario offset     # a 2 mm gap everywhere
    .venv/bin/python benchmarks/bench_evaluate.py --picture docs/img/evaluation_femur.png --samples 0

Scenario ``paper`` (default), as UltraBones100k is evaluated: the ground truth is the whole femur of
shared/data/bones (232k faces, 47,700 mm², the "CT model"); the raw "ultrasound" cloud is the
front-facing part of its upper three quarters (vertices with n_z > 0.1 and y > −120 mm, 0.3 mm
noise); the reconstruction is an open sheet over that part with a smooth 3 mm bump at the neck and a
±0.4 mm ripple; the pseudo ground truth keeps the ground-truth samples within τ = 2 mm of the raw
cloud. 5,000,000 samples are drawn on each mesh. ``offset``: the whole femur moved 2 mm inward
along its normals against the whole femur, a hard case for KD-trees (gap ≫ sample spacing).
Peak memory is the process's maximum resident set size (``resource.getrusage``), which includes
the meshes and the interpreter.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
FEMUR_CANDIDATES = [ROOT / "shared" / "data" / "bones" / "femur.ply",
                    ROOT.parent / "shared" / "data" / "bones" / "femur.ply",
                    Path("/work/shared/data/bones/femur.ply")]


def femur() -> trimesh.Trimesh:
    from ultraboneudf.io import load_mesh

    for p in FEMUR_CANDIDATES:
        if p.exists():
            return load_mesh(p)
    sys.exit("bench_evaluate: femur.ply not found in shared/data/bones")


def visible(gt: trimesh.Trimesh) -> np.ndarray:
    """Vertices a probe in front of the bone would see: front-facing, upper three quarters."""
    return (gt.vertex_normals[:, 2] > 0.1) & (gt.vertices[:, 1] > -120.0)


def raw_cloud(gt: trimesh.Trimesh, seed: int = 0) -> np.ndarray:
    """Stand-in for the raw ultrasound cloud: visible vertices with 0.3 mm Gaussian noise."""
    v = gt.vertices[visible(gt)]
    return v + np.random.default_rng(seed).normal(scale=0.3, size=v.shape)


def perturbed(gt: trimesh.Trimesh) -> trimesh.Trimesh:
    """An open reconstruction of the visible part: a 3 mm bump at the neck and a ±0.4 mm ripple."""
    v, n = gt.vertices, gt.vertex_normals
    bump = 3.0 * np.exp(-((v[:, 1] - 150.0) / 40.0) ** 2)
    ripple = 0.4 * np.sin(v[:, 0] / 6.0) * np.cos(v[:, 2] / 7.0)
    keep = visible(gt)[gt.faces].all(axis=1)
    return trimesh.Trimesh(v + n * (bump + ripple)[:, None], gt.faces[keep], process=False)


def offset(gt: trimesh.Trimesh, mm: float = 2.0) -> trimesh.Trimesh:
    return trimesh.Trimesh(gt.vertices - mm * gt.vertex_normals, gt.faces, process=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=5_000_000, help="per surface (0: skip the timing)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--scenario", default="paper", choices=["paper", "offset"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--picture", metavar="PNG", help="also render the example picture to PNG")
    ap.add_argument("--json", metavar="OUT", help="write the figures as JSON")
    args = ap.parse_args()

    sys.path.insert(0, str(ROOT / "src"))
    from ultraboneudf.evaluation import evaluate, reference_points, render_distance_png

    gt = femur()
    recon = perturbed(gt) if args.scenario == "paper" else offset(gt)
    raw = raw_cloud(gt, args.seed) if args.scenario == "paper" else None
    tau = 2.0 if raw is not None else None
    figures: dict = {"scenario": args.scenario, "samples_per_surface": args.samples, "device": args.device,
                     "cpu_count": os.cpu_count(), "gt_faces": int(len(gt.faces)),
                     "recon_faces": int(len(recon.faces))}
    if args.samples > 0:
        t0 = time.perf_counter()
        r = evaluate(recon, gt, raw_points=raw, pseudo_gt_mm=tau, samples=args.samples, seed=args.seed,
                     device=args.device)
        wall = time.perf_counter() - t0
        peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9  # Linux: KiB
        figures.update({"wall_s": round(wall, 2), "peak_rss_gb": round(peak_gb, 3),
                        "timings_s": {k: round(v, 2) for k, v in r.timings.items()},
                        "cd_mm": r.cd_mm, "hd95_mm": r.hd95_mm, "pseudo_gt_mm": r.pseudo_gt_mm,
                        "gt_samples_kept": r.samples_gt})
        if args.device == "cuda":
            import torch

            figures["gpu"] = torch.cuda.get_device_name(0)
        print(f"evaluate {args.samples:,} × {args.samples:,} samples ({args.scenario}, {args.device}, "
              f"{os.cpu_count()} cores): {wall:.1f} s, peak RSS {peak_gb:.2f} GB")
        print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in r.timings.items()))
        print(f"  CD {r.cd_mm:.4f} mm, HD95 {r.hd95_mm:.4f} mm, ground-truth samples kept {r.samples_gt:,} "
              f"(pseudo-GT τ = {r.pseudo_gt_mm} mm)")
    if args.picture:
        t0 = time.perf_counter()
        render_distance_png(args.picture, recon, reference_points(gt, raw, tau, 1_000_000, args.seed),
                            views=("front", "right", "back"), tile_height=420,
                            title="stand-in reconstruction vs. pseudo ground truth (femur)")
        print(f"picture {args.picture} ({os.path.getsize(args.picture) / 1e3:.0f} kB) in "
              f"{time.perf_counter() - t0:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
