"""Robustness: every method on ultrasound-like inputs of the four bones, at named noise levels.

Inputs (mm), per bone of ``../shared/data/bones`` (or ``ULTRABONEUDF_BONES``):

* sweep levels, from ``ultraboneudf simulate`` (the predicted masks compounded with the recorded,
  tracking-noisy poses, as ``reconstruct SWEEP`` does; truth: the visible surface, mesh faces seen
  by a beam): ``clean`` (noise level ``none``: exact path, poses and masks), ``moderate`` (0.3 mm
  noise along the beam, frames every 0.5 mm, the default segmentation errors), ``hard`` (0.8 mm
  noise along the beam, 3% of the scan lines a false echo up to 10 mm under the surface, frames
  every 1.5 mm with three 4 mm runs missing, tracking error 0.3 mm / 0.3° per frame) and ``real``
  (the false echoes of real segmentations: fascia sheets in front of the bone, streaks, clusters
  under it, an offset drifting along the sweep; ``ultraboneudf.synth.NOISE_PRESETS``), and
  ``real-cloud``: ``real``'s points without their probe positions and frames (a compounded cloud);
* ``open``: 100,000 area samples of the faces whose normal has a positive z component (the README's
  open femur), truth: that surface; ``e6-S``: the same samples with Gaussian noise of σ = S mm
  added (the paper's experiment E6), truth: the noise-free surface.

Metrics against the truth, over ``--samples`` area samples of each mesh: CD = ½(mean A→B + mean
B→A), HD95 = max of the two directed 95th percentiles (mm); ``area`` = mesh area / truth area;
``off_bone`` = the area of the mesh more than 1 mm from the whole bone model over the truth's area
(surface that is not bone: ``area`` less ``off_bone`` is mesh on the bone, which may lie outside the
visible truth where the probe saw no echo, e.g. a steep wall inside a bridged gap);
``loops`` = boundary loops; ``nm`` = edges shared by more than two faces; ``far`` = the sidecar's
``data_fit.input_far_fraction`` (input points > 3 mm from the mesh); ``time_s`` = end to end.
``cd_pgt_mm`` and ``hd95_pgt_mm``: the same against the paper's pseudo ground truth, the truth's
samples within 2 mm of an input point (the visible truth also holds surface that
no input point comes near, e.g. steep faces whose echoes the segmentation dropped).

    python benchmarks/bench_robust.py --levels hard --methods ultraboneudf,poisson,capudf
    python benchmarks/bench_robust.py --bones talus --levels clean,hard --preset fast
    python benchmarks/bench_robust.py --json bench_out/robust.jsonl --pictures bench_out/robust_png
    python benchmarks/bench_robust.py --levels hard --methods ultraboneudf --no-align
    python benchmarks/bench_robust.py --levels hard --methods ultraboneudf --no-fragments
    python benchmarks/bench_robust.py --bones talus --levels hard --sim pred_max_incidence_deg=75

``--describe`` only describes each input against the whole bone model (``bench_real.py
--describe``: distance bands, off-bone groups, the offset by the beam's incidence, with the sweeps'
own beams and the clouds' estimated from their frames).

``--sim`` changes one simulation option of the sweep levels (the last line: the segmentation keeps
echoes up to the visible truth's 75° incidence instead of fading them from 60°).

Rows are appended to ``--json`` as they finish (JSON lines); a rerun skips the rows already there
(same bone, level, seed, method, preset, iterations, ``--set``, ``--sim`` and the front end's
steps), so a killed run resumes. ``--no-fragments`` keeps the isolated fragments that neighbouring
frames do not confirm (the front end removes them by default).
Simulated inputs are cached under ``--cache`` (the sweep's points before the front end's outlier
removal, fragment filter and frame registration, which run again each time, so a change to those
steps is measured). ``--pictures`` renders each input's meshes coloured by their distance to the
truth (one column per method); ``--meshes`` keeps the meshes themselves (a row already in
``--json`` is not run again, so its mesh is not written).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_reconstruct import BONES  # noqa: E402

METHODS = "ultraboneudf,poisson,capudf,funsr,carotidudf,vanilla_udf,ultraboneudf_pull"
SWEEP_LEVELS = {"clean": "none", "moderate": "moderate", "hard": "hard", "real": "real"}
CLOUD_LEVELS = {"real-cloud": "real"}  # a sweep level's points without their probe positions and frames
OFF_BONE_MM = 1.0
BONE_SAMPLES = 2_000_000  # 0.16 mm apart on the largest bone's 50,000 mm²: far below OFF_BONE_MM
LEVELS = "clean,moderate,hard,open,e6-0.5,e6-1.0,e6-1.5,e6-2.0"


def make_input(bone: str, level: str, seed: int, cache: Path, align: bool = True,
               sim: dict | None = None, no_fragments: bool = False):
    """(points (N, 3) mm, probe positions (N, 3) mm or None, truth mesh, frame indices (N,) or None)
    of one bone at one level;
    ``align``: the sweep's frames registered to their neighbours, as ``reconstruct SWEEP`` does
    (``--no-align``: not); ``sim``: simulation options over the level's (sweep levels only);
    ``no_fragments``: keep the fragments that neighbouring frames do not confirm.

    ``cache`` keeps what the simulator made (the compounded points with their provenance, and the
    truth), so that a later run skips the simulation; the outliers are removed and the frames
    registered on every run, since those are the front end's own steps and their code may have
    changed since the cache was written."""
    import trimesh

    from ultraboneudf import load_mesh
    from ultraboneudf.synth import facing_surface

    cloud_only = level in CLOUD_LEVELS
    level = CLOUD_LEVELS.get(level, level)
    if level not in SWEEP_LEVELS and level != "open" and not level.startswith("e6-"):
        raise SystemExit(f"unknown level {level!r}; choose from {LEVELS}")
    mesh = load_mesh(BONES / f"{bone}.ply")
    tag = f"{bone}_{level}_s{seed}"
    if level in SWEEP_LEVELS:
        from ultraboneudf.synth.simulator import config_with_noise
        from ultraboneudf.synth.visible_truth import truth_beam_spacing

        sim_cfg = config_with_noise(SWEEP_LEVELS[level], seed=seed, **(sim or {}))
        # the truth's beam spacing and every simulation setting name the cache, so a truth sampled
        # by another rule, or a level whose settings have changed since, is not reused
        tag += f"_sweep_beam{truth_beam_spacing(mesh, sim_cfg):.4f}"
        tag += "".join(f"_{k}{v}" for k, v in sorted((sim or {}).items()))
        settings = json.dumps(dataclasses.asdict(sim_cfg), sort_keys=True, default=str)
        tag += f"_cfg{hashlib.sha1(settings.encode()).hexdigest()[:8]}_raw"
    tag = cache / tag
    if not (tag / "points.npz").exists():
        tag.mkdir(parents=True, exist_ok=True)
        if level in SWEEP_LEVELS:
            from ultraboneudf.sweep.front_end import SweepOptions, sweep_points
            from ultraboneudf.synth.simulator import simulate_sweep

            sim = simulate_sweep(mesh, sim_cfg)
            truth = sim.visible_mesh
            raw = SweepOptions(segment="masks", remove_outliers=False, drop_fragments=False, align_frames=False)
            arrays = dataclasses.asdict(sweep_points(sim.sweep, raw).cloud)
        else:
            truth = facing_surface(mesh, (0.0, 0.0, 1.0))
            points = trimesh.sample.sample_surface(truth, 100_000, seed=seed)[0]
            if level != "open":
                sigma = float(level[3:])
                points = points + np.random.default_rng(seed + 1000).normal(0.0, sigma, points.shape)
            arrays = {"points": points}
        truth.export(tag / "truth.ply")
        np.savez(tag / "points.npz", **arrays)  # last: its presence marks a complete entry
    data = dict(np.load(tag / "points.npz"))
    truth = load_mesh(tag / "truth.ply")
    if level not in SWEEP_LEVELS:
        return data["points"], None, truth, None
    from ultraboneudf.sweep.compound import CompoundedPoints
    from ultraboneudf.sweep.front_end import SweepOptions, clean_points

    # the front end's own steps after compounding, with its defaults
    cp = clean_points(CompoundedPoints(**data), SweepOptions(drop_fragments=not no_fragments, align_frames=align))[0]
    if cloud_only:
        return cp.points, None, truth, None
    return cp.points, cp.probe_position, truth, cp.frame_index


def parse_sim(items: list[str]) -> dict:
    """``--sim KEY=VALUE`` items as simulation options, parsed as ``ultraboneudf simulate --set``
    parses them (the seed is the benchmark's own ``--seed``)."""
    from ultraboneudf.cli.cmd_simulate import parse_assignments
    from ultraboneudf.errors import InputError

    try:
        sim = parse_assignments(items)
    except InputError as exc:
        raise SystemExit(f"--sim: {exc}") from None
    if "seed" in sim:
        raise SystemExit("--sim: the simulation's seed is --seed")
    return sim


def bone_tree(bone: str):
    """A KD-tree of dense area samples of the whole bone model (mm), for :func:`off_bone_area`."""
    from ultraboneudf import load_mesh
    from ultraboneudf.evaluation.sampling import sample_surface
    from ultraboneudf.geometry.neighbors import kd_tree

    return kd_tree(sample_surface(load_mesh(BONES / f"{bone}.ply"), BONE_SAMPLES, seed=0))


def off_bone_area(mesh, truth_area: float, tree, samples: int) -> float:
    """The area of ``mesh`` farther than ``OFF_BONE_MM`` from the bone (``tree``: :func:`bone_tree`)
    over ``truth_area``, from ``samples`` area samples of the mesh."""
    from ultraboneudf.evaluation.sampling import sample_surface

    d = tree.query(sample_surface(mesh, samples, seed=0), k=1, workers=-1)[0]
    return float(mesh.area * np.mean(d > OFF_BONE_MM) / truth_area)


def run_one(method: str, points, probe, truth, args: argparse.Namespace, frames=None,
            bone_kd=None) -> tuple[dict, object]:
    """One reconstruction and its scores (``bone_kd``: :func:`bone_tree` of the bone, for
    ``off_bone``); returns the row and the mesh (``None`` on failure)."""
    import ultraboneudf
    from ultraboneudf.errors import InputError
    from ultraboneudf.evaluation import evaluate

    overrides = {"train.iters": args.iters} if args.iters and method != "poisson" else {}
    t0 = time.perf_counter()
    try:
        rec = ultraboneudf.reconstruct(points, preset=args.preset, device=args.device, seed=args.seed,
                                       method=method, assignments=args.set, probe_positions=probe, frame_index=frames,
                                       **overrides)
    except InputError as exc:  # e.g. the Poisson extra is not installed
        return {"error": str(exc)}, None
    row = {"time_s": round(time.perf_counter() - t0, 1), "points": len(points),
           "iters": rec.config.train.iters if method != "poisson" else None}
    if rec.mesh is None:
        return {**row, "failed": True}, None
    res = evaluate(rec.mesh, truth, samples=args.samples, seed=0)
    # the paper's protocol beside it: the truth only within 2 mm of an input point
    pgt = evaluate(rec.mesh, truth, raw_points=points, pseudo_gt_mm=2.0, samples=args.samples, seed=0)
    q = rec.quality
    row.update(cd_mm=round(res.cd_mm, 3), hd95_mm=round(res.hd95_mm, 2),
               cd_pgt_mm=round(pgt.cd_mm, 3), hd95_pgt_mm=round(pgt.hd95_mm, 2),
               d_rg_mm=round(res.d_rg_mean_mm, 3), d_gr_mm=round(res.d_gr_mean_mm, 3),
               area=round(float(rec.mesh.area / truth.area), 3),
               off_bone=(None if bone_kd is None
                         else round(off_bone_area(rec.mesh, truth.area, bone_kd, args.samples), 3)),
               loops=q.get("boundary_loops"),
               nm=q.get("nonmanifold_edges"), components=q.get("components"),
               far=round(rec.data_fit.get("input_far_fraction", float("nan")), 4),
               outliers=rec.counts.get("outliers_removed"), depth=rec.counts.get("extract_depth"))
    return row, rec.mesh


COLUMNS = ["bone", "level", "method", "cd_mm", "hd95_mm", "cd_pgt_mm", "hd95_pgt_mm", "area", "off_bone", "loops", "nm",
           "far", "time_s"]


def print_table(rows: list[dict]) -> None:
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for r in rows:
        cells = [("" if r.get(c) is None else str(r.get(c))) for c in COLUMNS]
        if r.get("failed"):
            cells[3] = "no surface"
        if r.get("error"):
            cells[3] = f"not run: {r['error']}"
        print("| " + " | ".join(cells) + " |")
    print_comparison(rows)


def print_comparison(rows: list[dict], ours: str = "ultraboneudf", others=("poisson", "capudf")) -> None:
    """Per (bone, level): our CD over the better of the baselines' (a ratio below 1: ours is lower)."""
    cases = sorted({(r["bone"], r["level"]) for r in rows})
    lines = []
    for bone, level in cases:
        by = {r["method"]: r for r in rows if (r["bone"], r["level"]) == (bone, level) and r.get("cd_mm")}
        base = [by[m]["cd_mm"] for m in others if m in by]
        if ours in by and base:
            lines.append(f"| {bone} | {level} | {by[ours]['cd_mm']} | {min(base)} | "
                         f"{by[ours]['cd_mm'] / min(base):.2f} |")
    if lines:
        print(f"\n| bone | level | {ours} CD | best of {', '.join(others)} CD | ratio |")
        print("|---|---|---|---|---|")
        print("\n".join(lines))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bones", default="femur,pelvis,talus,tibia")
    p.add_argument("--levels", default=LEVELS)
    p.add_argument("--methods", default=METHODS)
    p.add_argument("--preset", default="robust")
    p.add_argument("--iters", type=int, default=None, help="training steps of every neural method")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                   help="a simulation option over the sweep levels' own (a field of "
                        "ultraboneudf.synth.SimulationConfig, e.g. pred_max_incidence_deg=75)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulation and of every method")
    p.add_argument("--no-align", action="store_true", help="keep the sweeps' frames as tracked "
                   "(reconstruct --no-align-frames)")
    p.add_argument("--no-fragments", action="store_true", help="keep the isolated fragments that "
                   "neighbouring frames do not confirm (reconstruct --no-consistency)")
    p.add_argument("--samples", type=int, default=300_000, help="area samples per mesh for CD/HD95")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--cache", type=Path, default=Path("bench_out/robust_inputs"))
    p.add_argument("--json", type=Path, help="append each row to this JSON-lines file; skip rows already in it")
    p.add_argument("--pictures", type=Path, help="write one distance-coloured PNG per input here")
    p.add_argument("--meshes", type=Path, help="write each mesh here (BONE_LEVEL_sSEED_METHOD.ply, mm)")
    p.add_argument("--describe", action="store_true", help="only describe each input against the whole bone "
                   "model, as bench_real.py --describe describes real inputs against their CT")
    args = p.parse_args()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    done: list[dict] = []
    if args.json and args.json.exists():
        done = [json.loads(line) for line in args.json.read_text().splitlines() if line.strip()]
    sim = parse_sim(args.sim)
    rows = []
    for bone in args.bones.split(","):
        tree = None
        for level in args.levels.split(","):
            points, probe, truth, frames = make_input(bone, level, args.seed, args.cache, not args.no_align,
                                                      sim, args.no_fragments)
            if args.describe:
                from bench_real import Truth, describe

                from ultraboneudf import load_mesh

                model = Truth(load_mesh(BONES / f"{bone}.ply"), points, samples=BONE_SAMPLES)
                print(f"{bone} {level}: {json.dumps(describe(points, model, probe))}", flush=True)
                continue
            meshes = {}
            for method in args.methods.split(","):
                key = {"bone": bone, "level": level, "seed": args.seed, "method": method,
                       "preset": args.preset, "iters_override": args.iters, "set": args.set}
                if level in SWEEP_LEVELS or level in CLOUD_LEVELS:
                    key["align"] = not args.no_align
                    key["sim"] = args.sim
                    key["fragments"] = not args.no_fragments
                # rows written before --sim and the fragment filter existed have neither: they
                # were made without them
                missing = {"sim": [], "fragments": False}
                old = next((r for r in done if all(r.get(k, missing.get(k)) == v
                                                   for k, v in key.items())), None)
                if old is not None:
                    rows.append(old)
                    continue
                tree = tree if tree is not None else bone_tree(bone)
                row, mesh = run_one(method, points, probe, truth, args, frames, tree)
                rows.append({**key, **row})
                print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
                if args.json:
                    args.json.parent.mkdir(parents=True, exist_ok=True)
                    with args.json.open("a") as f:
                        f.write(json.dumps(rows[-1]) + "\n")
                meshes[method] = mesh
                if args.meshes and mesh is not None:
                    args.meshes.mkdir(parents=True, exist_ok=True)
                    mesh.export(args.meshes / f"{bone}_{level}_s{args.seed}_{method}.ply")
            if args.pictures and meshes:
                import trimesh

                from ultraboneudf.evaluation.render import render_grid_png

                args.pictures.mkdir(parents=True, exist_ok=True)
                render_grid_png(args.pictures / f"{bone}_{level}.png", meshes,
                                trimesh.sample.sample_surface(truth, 200_000, seed=0)[0], views=("front", "top"),
                                ground_truth=truth)
    if not args.describe:
        print_table(rows)


if __name__ == "__main__":
    main()
