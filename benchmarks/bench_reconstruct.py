"""End-to-end reconstruction benchmark: seconds per stage, iterations per second, peak memory and
Chamfer distance, per preset and device.

Input: the open femur of the tests and the README, the faces of ``femur.ply`` whose normal has a
positive z component, 100,000 area samples (mm) — or the built-in phantom. Accuracy: CD = ½(mean A→B + mean B→A)
nearest-neighbour distance over ``--samples`` area samples of each mesh, HD95 = max of the two
directed 95th percentiles (mm).

    python benchmarks/bench_reconstruct.py --presets official,fast --devices cpu
    python benchmarks/bench_reconstruct.py --presets fast --input phantom --iters 500
    python benchmarks/bench_reconstruct.py --presets official --threads 1 --checkpoint bench_out/ckpt

Each configuration runs in a fresh subprocess, so peak host memory (max RSS) is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BONES = Path(os.environ.get("ULTRABONEUDF_BONES", Path(__file__).resolve().parents[2] / "shared/data/bones"))


def make_input(name: str, seed: int = 0):
    """(points mm (N,3), truth mesh) for ``femur`` (open, z-facing) or ``phantom``."""
    import trimesh

    from ultraboneudf import load_mesh
    from ultraboneudf.synth import bone_phantom, facing_surface

    if name == "phantom":
        ph = bone_phantom(seed=seed)
        return ph.points, ph.truth
    bone = BONES / f"{name}.ply"
    truth = facing_surface(load_mesh(bone), (0.0, 0.0, 1.0))
    return trimesh.sample.sample_surface(truth, 100_000, seed=seed)[0], truth


def run_one(args: argparse.Namespace) -> list[dict]:
    """One preset on one device: its row, then one row per ``--reextract`` of the same field."""
    import torch

    import ultraboneudf
    from ultraboneudf.checkpoints import Checkpoint, fingerprint

    torch.set_num_threads(args.threads or torch.get_num_threads())
    points, truth = make_input(args.input)
    overrides = {"train.iters": args.iters} if args.iters else {}
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    if args.checkpoint:
        # a long CPU run (30,000 official steps) spans sessions: resume it where it was killed
        # (one file per configuration: a checkpoint of another configuration is refused, not resumed)
        args.checkpoint.mkdir(parents=True, exist_ok=True)
        tag = fingerprint(args.iters, args.set)[:8]
        overrides["checkpoint"] = Checkpoint(
            args.checkpoint / f"{args.input}_{args.preset}_{args.device}_s{args.seed}_{tag}.pt", every=250,
            resume=True)
    rec = ultraboneudf.reconstruct(points, preset=args.preset, device=args.device, seed=args.seed,
                                   quiet=not args.verbose, assignments=args.set, **overrides)
    wall = time.perf_counter() - t0
    row = {"preset": args.preset, "device": rec.device, "input": args.input, "points": len(points),
           "iters": rec.config.train.iters, **{k: round(v, 2) for k, v in rec.timings.items()},
           "wall_s": round(wall, 2),
           "it_per_s": round(rec.config.train.iters / max(rec.timings["train_s"], 1e-9), 1),
           "peak_host_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 0),
           "peak_gpu_mb": (round(torch.cuda.max_memory_allocated() / 2**20, 0)
                           if args.device.startswith("cuda") else None),
           "faces": rec.counts["faces"], "set": args.set}
    if rec.mesh is None:
        row.update(cd_mm=None, hd95_mm=None, failed=True)
    else:
        row["nonmanifold_edges"] = rec.quality.get("nonmanifold_edges")
        # the self-check without ground truth, next to the truth-based figures it should agree with
        row["input_far"] = round(rec.data_fit.get("input_far_fraction", float("nan")), 4)
        row["mesh_far_area"] = round(rec.data_fit.get("mesh_far_area_fraction", float("nan")), 4)
        row.update(score(rec.mesh, truth, args.samples))
        with tempfile.TemporaryDirectory() as tmp:
            target = Path(args.save) if args.save else Path(tmp) / "mesh.ply"
            target.parent.mkdir(parents=True, exist_ok=True)
            t1 = time.perf_counter()
            rec.save(target)
            row["write_s"] = round(time.perf_counter() - t1, 3)
    e = rec.config.extract
    row["extract_mode"] = f"{e.mode}@{e.max_depth}@{e.trim_mm:g}"
    if args.save_field and rec.field is not None:
        torch.save({"state_dict": rec.field.net.state_dict(), "config": rec.config.to_dict(),
                    "normalizer": rec.normalizer.to_dict()}, args.save_field)
    return [row] + [reextract(rec, truth, spec, args.samples) for spec in args.reextract]


def reextract(rec, truth, spec: str, samples: int) -> dict:
    """The same trained field extracted again as ``MODE@DEPTH`` or ``MODE@DEPTH@TRIM_MM`` (the
    modes side by side); without a trim value the preset's ``extract.trim_mm`` applies."""
    from ultraboneudf.extraction import mesh_quality

    mode, depth, *trim = spec.split("@")
    settings = {"mode": mode, "max_depth": int(depth), **({"trim_mm": float(trim[0])} if trim else {})}
    t0 = time.perf_counter()
    mesh = rec.extract(**settings)
    seconds = time.perf_counter() - t0
    row = {"preset": rec.preset, "device": rec.device, "extract_mode": spec, "extract_s": round(seconds, 2)}
    if mesh is None or len(mesh.faces) == 0:
        return {**row, "cd_mm": None, "hd95_mm": None, "failed": True}
    return {**row, "faces": len(mesh.faces), **score(mesh, truth, samples),
            "nonmanifold_edges": mesh_quality(mesh).get("nonmanifold_edges")}


def score(mesh, truth, samples: int) -> dict:
    """CD, HD95 (mm) and area ratio of ``mesh`` against ``truth``."""
    from ultraboneudf.evaluation import evaluate

    res = evaluate(mesh, truth, samples=samples, seed=0)
    return {"cd_mm": round(res.cd_mm, 4), "hd95_mm": round(res.hd95_mm, 4),
            "area_ratio": round(float(mesh.area / truth.area), 3)}


def print_table(rows: list[dict]) -> None:
    cols = ["preset", "device", "extract_mode", "iters", "preprocess_s", "train_s", "extract_s", "total_s",
            "it_per_s", "peak_host_mb", "peak_gpu_mb", "faces", "area_ratio", "nonmanifold_edges", "cd_mm",
            "hd95_mm", "input_far", "mesh_far_area"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join("" if r.get(c) is None else str(r.get(c)) for c in cols) + " |")
    # per-stage profile: the pipeline's own steps, in the order they run
    stages = ["voxel_s", "subset_s", "sigma_s", "queries_s", "anchors_s", "static_nn_s", "train_s",
              "extract_s", "write_s"]
    print()
    print("| preset | device | " + " | ".join(stages) + " |")
    print("|" + "---|" * (len(stages) + 2))
    for r in (r for r in rows if "iters" in r):  # training runs, not re-extractions
        print(f"| {r['preset']} | {r['device']} | " + " | ".join(str(r.get(c, "")) for c in stages) + " |")
    print()
    base = {r["device"]: r for r in rows if r["preset"] == "official" and r.get("total_s")}
    for r in rows:
        ref = base.get(r["device"])
        if ref and r is not ref and r.get("total_s"):
            print(f"{r['preset']} on {r['device']}: {ref['total_s'] / r['total_s']:.1f}x faster than official, "
                  f"CD {r['cd_mm']} vs {ref['cd_mm']} mm")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--presets", default="fast,official")
    p.add_argument("--devices", default="cpu")
    p.add_argument("--input", default="femur", help="femur, tibia, pelvis, talus (z-facing open part) or phantom")
    p.add_argument("--iters", type=int, default=None, help="override the preset's iterations")
    p.add_argument("--samples", type=int, default=1_000_000, help="area samples per mesh for CD/HD95")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--json", type=Path, help="also write the rows as JSON")
    p.add_argument("--save", default=None, help="(single run) write the mesh and sidecar here")
    p.add_argument("--save-field", default=None, help="(single run) torch.save the trained network here")
    p.add_argument("--reextract", action="append", default=[], metavar="MODE@DEPTH",
                   help="also extract the same field as e.g. clean@8, faithful@9 or faithful@9@0 "
                        "(the last number: extract.trim_mm; repeatable)")
    p.add_argument("--checkpoint", type=Path, default=None, metavar="DIR",
                   help="save each training run's state in DIR every 250 steps and resume from it")
    p.add_argument("--verbose", action="store_true", help="show progress bars")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--preset", help=argparse.SUPPRESS)
    p.add_argument("--device", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        for row in run_one(args):
            print("ROW " + json.dumps(row), flush=True)
        return
    rows = []
    for device in args.devices.split(","):
        for name in args.presets.split(","):
            cmd = [sys.executable, __file__, "--one", "--preset", name, "--device", device, "--input", args.input,
                   "--samples", str(args.samples), "--seed", str(args.seed)]
            for flag, value in (("--iters", args.iters), ("--threads", args.threads), ("--save", args.save),
                                ("--save-field", args.save_field), ("--checkpoint", args.checkpoint)):
                if value:
                    cmd += [flag, str(value)]
            for spec in args.reextract:
                cmd += ["--reextract", spec]
            for item in args.set:
                cmd += ["--set", item]
            if args.verbose:
                cmd.append("--verbose")
            out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=False,
                                 stderr=None if args.verbose else subprocess.PIPE)
            lines = [ln for ln in out.stdout.splitlines() if ln.startswith("ROW ")]
            if not lines:
                print(f"{name} on {device} failed:\n{out.stderr}", file=sys.stderr)
                continue
            for ln in lines:
                rows.append(json.loads(ln[4:]))
                print(json.dumps(rows[-1]), file=sys.stderr)
    print_table(rows)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
