"""Every method on the open and the closed femur: CD and HD95 (mm), area ratio, run time, device.

Inputs: ``femur.ply`` whole (closed) and its faces whose normal has a positive z component (open,
the ultrasound-like view of the tests); 100,000 area samples of each (mm). Accuracy against the
same surface the points were drawn from: CD = ½(mean A→B + mean B→A), HD95 = max of the two
directed 95th percentiles, over ``--samples`` area samples of each mesh. ``area`` is the mesh area
over the truth's area: an open truth meshed as a closed or doubled surface shows up as ≈ 2 or more.

    python benchmarks/bench_methods.py --iters 6000 --json bench_out/methods.json
    python benchmarks/bench_methods.py --methods ultraboneudf,poisson --inputs open

Every method runs with the same preset (``fast`` by default: each method keeps its own network,
loss and extractor, and trains for the preset's steps, or ``--iters``) and seed. Rows are printed
as they finish (and appended to ``--json``), then the whole table. Poisson needs the ``[poisson]``
extra; a method that fails or finds no surface gets a row saying so.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_reconstruct import BONES  # noqa: E402

METHODS = "ultraboneudf,ultraboneudf_pull,vanilla_udf,carotidudf,capudf,funsr,poisson"


def make_inputs(which: list[str], seed: int = 0) -> dict:
    """{name: (points mm (N, 3), truth mesh)} for ``open`` and ``closed`` femur."""
    import trimesh

    from ultraboneudf import load_mesh
    from ultraboneudf.synth import facing_surface

    femur = load_mesh(BONES / "femur.ply")
    out = {}
    for name in which:
        truth = facing_surface(femur, (0.0, 0.0, 1.0)) if name == "open" else femur
        out[name] = (trimesh.sample.sample_surface(truth, 100_000, seed=seed)[0], truth)
    return out


def run_one(method: str, points: np.ndarray, truth, args: argparse.Namespace) -> dict:
    import ultraboneudf
    from ultraboneudf.errors import InputError
    from ultraboneudf.evaluation import evaluate

    overrides = {"train.iters": args.iters} if args.iters and method != "poisson" else {}
    t0 = time.perf_counter()
    try:
        rec = ultraboneudf.reconstruct(points, preset=args.preset, device=args.device, seed=args.seed,
                                       method=method, quiet=True, **overrides)
    except InputError as exc:  # e.g. the Poisson extra is not installed
        return {"method": method, "error": str(exc)}
    row = {"method": method, "device": rec.device, "iters": rec.config.train.iters,
           "time_s": round(time.perf_counter() - t0, 1)}
    if rec.mesh is None:
        return {**row, "failed": True}
    res = evaluate(rec.mesh, truth, samples=args.samples, seed=0)
    return {**row, "cd_mm": round(res.cd_mm, 3), "hd95_mm": round(res.hd95_mm, 2),
            "area": round(float(rec.mesh.area / truth.area), 2), "faces": len(rec.mesh.faces)}


def print_table(rows: list[dict]) -> None:
    cols = ["input", "method", "cd_mm", "hd95_mm", "area", "time_s", "iters", "device"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        cells = [str(r.get(c, "")) for c in cols]
        if r.get("failed"):
            cells[2] = "no surface"
        if r.get("error"):
            cells[2] = f"not run: {r['error']}"
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default=METHODS)
    p.add_argument("--inputs", default="open,closed")
    p.add_argument("--preset", default="fast")
    p.add_argument("--iters", type=int, default=None, help="training steps of every neural method")
    p.add_argument("--device", default="auto")
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--json", type=Path, help="append each row to this JSON-lines file")
    args = p.parse_args()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    rows = []
    for name, (points, truth) in make_inputs(args.inputs.split(",")).items():
        for method in args.methods.split(","):
            row = {"input": name, **run_one(method, points, truth, args)}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
            if args.json:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                with args.json.open("a") as f:
                    f.write(json.dumps(row) + "\n")
    print_table(rows)


if __name__ == "__main__":
    main()
