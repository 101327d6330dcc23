"""Sweep front end on simulated sweeps of every bone in ../shared/data/bones (and the real sample).

For each bone: simulate a tracked sweep with the simulator's default noise, then score
  * segmentation: pixel precision / recall of the classical detector (and of the simulator's
    "predicted" masks) against the true masks, tolerance 0.5 mm, summed over all frames;
  * compounding: the bone points from the classical detector (and from the predicted masks),
    compounded with the *noisy* recorded poses, top boundary per scan line, outlier removal:
    median and 90th-percentile distance to the closed true surface (mm, point → mesh, exact),
    and coverage of the visible true surface (fraction of its area within 1 mm of a point).

Usage:
    python benchmarks/bench_sweep.py [--bones DIR] [--json OUT.json] [--figures docs/img]
                                     [--real SAMPLE_DIR]

``--figures`` also writes the pictures of docs/sweep.md (segmentation overlays of the real sample's
30 sweep frames and 14 example frames, renders of the compounded real and simulated points,
simulated frames with true and detected bone). Takes about 3-4 minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ultraboneudf.io import load_mesh
from ultraboneudf.pictures import save_picture
from ultraboneudf.sweep import BoneDetector, read_sweep, sweep_to_points
from ultraboneudf.sweep.bone import classical_bone_masks
from ultraboneudf.sweep.figures import contact_sheet, mark_dilation, overlay, render_points
from ultraboneudf.sweep.formats.images import read_image
from ultraboneudf.synth.scoring import mask_precision_recall, point_to_mesh_distance, surface_coverage
from ultraboneudf.synth.simulator import SimulationConfig, simulate_sweep

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
TOL_MM = 0.5
COVER_MM = 1.0


def score_points(points: np.ndarray, sim) -> dict[str, float]:
    d = point_to_mesh_distance(points, sim.closed_mesh)
    return {"points": int(len(points)), "median_mm": float(np.median(d)),
            "p90_mm": float(np.percentile(d, 90)),
            "coverage": surface_coverage(sim.visible_mesh, points, COVER_MM)}


def bench_bone(path: Path, detector: BoneDetector, figures: Path | None) -> dict:
    mesh = load_mesh(path)
    t0 = time.perf_counter()
    sim = simulate_sweep(mesh, SimulationConfig(seed=0))
    t_sim = time.perf_counter() - t0
    s = sim.config.spacing_mm
    t0 = time.perf_counter()
    det_masks, _ = classical_bone_masks(sim.sweep, detector)
    t_seg = time.perf_counter() - t0
    p_det, r_det = mask_precision_recall(det_masks, sim.true_masks, s, TOL_MM)
    p_pred, r_pred = mask_precision_recall(sim.pred_masks, sim.true_masks, s, TOL_MM)
    cp_det = sweep_to_points(sim.sweep, masks=det_masks, segment="masks")
    cp_pred = sweep_to_points(sim.sweep, segment="masks")
    row = {"bone": path.stem, "frames": sim.sweep.n_frames,
           "sweep_mm": sim.info["sweep_length_mm"], "visible_area_mm2": sim.info["visible_area_mm2"],
           "simulate_s": t_sim, "segment_s_per_frame": t_seg / sim.sweep.n_frames,
           "classical": {"precision": p_det, "recall": r_det, **score_points(cp_det.points, sim)},
           "predicted_masks": {"precision": p_pred, "recall": r_pred, **score_points(cp_pred.points, sim)}}
    if figures is not None:
        idx = np.linspace(0, sim.sweep.n_frames - 1, 7).astype(int)[1:-1][::2][:3]
        row["_tiles"] = [overlay(sim.sweep.images[i], det_masks[i], truth=sim.true_masks[i], dilate=mark_dilation(sim.sweep.width, 256))
                         for i in idx]
        row["_tile_labels"] = [f"{path.stem} frame {i}" for i in idx]
        save_picture(render_points(cp_det.points, cp_det.frame_index, width=900, panel_height=200,
                               title=f"{path.stem}: simulated sweep, classical detector"),
                 figures / f"sweep_sim_points_{path.stem}.png", max_colours=96)
    return row


def real_figures(sample: Path, detector: BoneDetector, figures: Path) -> dict:
    sweep = read_sweep(sample)
    masks, _ = classical_bone_masks(sweep, detector)
    tiles = [overlay(sweep.images[i], masks[i], dilate=mark_dilation(sweep.width, 240))
             for i in range(sweep.n_frames)]
    save_picture(contact_sheet(tiles, [f"{n}" for n in sweep.frame_names], columns=6, tile_width=240),
             figures / "sweep_real_overlays.jpg")
    ex_files = sorted((sample / "examples").glob("*.png"))
    ex_tiles = []
    for f in ex_files:
        img = read_image(f)
        ex_tiles.append(overlay(img, detector.segment(img, 0.05392), dilate=mark_dilation(img.shape[1], 300)))
    save_picture(contact_sheet(ex_tiles, [f.name for f in ex_files], columns=5, tile_width=300),
             figures / "sweep_examples_overlays.jpg")
    cp = sweep_to_points(sweep, masks=masks, segment="masks")
    save_picture(render_points(cp.points, cp.frame_index, width=1000, panel_height=220,
                           title="UltraBones100k sample: 30 frames, classical detector (CT frame)"),
             figures / "sweep_real_points.png", max_colours=96)
    frames = np.bincount(cp.frame_index, minlength=sweep.n_frames)
    return {"points": int(len(cp)), "frames_with_bone": int((frames > 0).sum()),
            "extent_mm": np.ptp(cp.points, axis=0).round(1).tolist()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bones", type=Path, default=SHARED / "bones")
    ap.add_argument("--real", type=Path, default=SHARED / "ultrabones100k_sample")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--figures", type=Path, default=None, help="write the docs pictures here")
    args = ap.parse_args(argv)
    detector = BoneDetector()
    if args.figures is not None:
        args.figures.mkdir(parents=True, exist_ok=True)
    rows = []
    for path in sorted(args.bones.glob("*.ply")):
        print(f"… {path.stem}", file=sys.stderr, flush=True)
        rows.append(bench_bone(path, detector, args.figures))
    header = (f"{'bone':<8} {'frames':>6} | {'classical detector':^44} | {'simulated predicted masks':^44}\n"
              f"{'':<8} {'':>6} | {'prec':>6} {'recall':>6} {'median':>8} {'p90':>7} {'cover':>6} {'pts':>7} |"
              f" {'prec':>6} {'recall':>6} {'median':>8} {'p90':>7} {'cover':>6} {'pts':>7}")
    print(header)
    for r in rows:
        line = f"{r['bone']:<8} {r['frames']:>6} |"
        for key in ("classical", "predicted_masks"):
            m = r[key]
            line += (f" {m['precision']:6.3f} {m['recall']:6.3f} {m['median_mm']:6.3f}mm "
                     f"{m['p90_mm']:5.2f}mm {m['coverage']:6.3f} {m['points']:7d} |")
        print(line.rstrip("|"))
    print(f"(precision/recall: pixels within {TOL_MM} mm of the other mask; median/p90: point → closed "
          f"true surface; cover: fraction of the visible true surface within {COVER_MM} mm of a point)")
    ok = all(r["classical"]["median_mm"] <= 0.5 and r["classical"]["coverage"] >= 0.8 for r in rows)
    print(f"targets (classical: median ≤ 0.5 mm, coverage ≥ 80%): {'met' if ok else 'NOT met'}")
    result = {"bones": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]}
    if args.figures is not None:
        tiles = [t for r in rows for t in r["_tiles"]]
        labels = [t for r in rows for t in r["_tile_labels"]]
        save_picture(contact_sheet(tiles, labels, columns=6, tile_width=256),
                 args.figures / "sweep_sim_overlays.jpg")
        if args.real.is_dir():
            result["real_sample"] = real_figures(args.real, detector, args.figures)
            print(f"real sample: {result['real_sample']}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
