"""How pre-processing grows with the input: a reconstruction of 10⁵, 10⁶ and 10⁷ points, seconds per
stage and peak resident memory, each size in a fresh process.

Input: area samples of the open femur (``../shared/data/bones/femur.ply``, the faces whose normal
has a positive z component) with 0.2 mm Gaussian noise, in mm. The run is ``reconstruct`` with
``--preset`` (default ``fast``) and ``--iters`` training steps (default 300: the training is not
what is measured).

    python benchmarks/bench_scale.py --sizes 100000,1000000,10000000
    python benchmarks/bench_scale.py --sizes 1000000 --preset robust
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_reconstruct import BONES  # noqa: E402

CHILD = r"""
import json, resource, sys, time
import numpy as np
import trimesh
import ultraboneudf
from ultraboneudf.synth import facing_surface
n, preset, iters = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
truth = facing_surface(ultraboneudf.load_mesh(sys.argv[4]), (0.0, 0.0, 1.0))
pts = trimesh.sample.sample_surface(truth, n, seed=0)[0] + np.random.default_rng(1).normal(0.0, 0.2, (n, 3))
t0 = time.perf_counter()
rec = ultraboneudf.reconstruct(pts, preset=preset, device="cpu", seed=0, **{"train.iters": iters})
wall = time.perf_counter() - t0
peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
print(json.dumps({"n": n, "wall_s": wall, "peak_gb": peak_gb, "timings": rec.timings,
                  "voxelised": rec.counts["voxelized_points"]}))
"""

STAGES = ("voxel_s", "surface_fit_s", "subset_s", "sigma_s", "queries_s", "anchors_s", "static_nn_s",
          "preprocess_s", "train_s", "extract_s", "fit_s")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="100000,1000000,10000000")
    p.add_argument("--preset", default="fast")
    p.add_argument("--iters", type=int, default=300)
    args = p.parse_args()
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        res = subprocess.run([sys.executable, "-c", CHILD, str(n), args.preset, str(args.iters),
                              str(BONES / "femur.ply")], capture_output=True, text=True)
        if res.returncode:
            print(res.stderr[-2000:], file=sys.stderr)
            continue
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    stages = [s for s in STAGES if any(s in r["timings"] for r in rows)]
    print("| points | voxelised | " + " | ".join(stages) + " | total s | peak GB |")
    print("|---:|---:|" + "---:|" * (len(stages) + 2))
    for r in rows:
        cells = [f"{r['timings'][s]:.1f}" if s in r["timings"] else "" for s in stages]
        print(f"| {r['n']:,} | {r['voxelised']:,} | " + " | ".join(cells) + f" | {r['timings']['total_s']:.1f} | {r['peak_gb']:.2f} |")
    if len(rows) > 1:
        a, b = rows[0], rows[-1]
        print(f"\n{b['n'] / a['n']:.0f}× the points: {b['timings']['preprocess_s'] / a['timings']['preprocess_s']:.1f}× "
              "the pre-processing time")


if __name__ == "__main__":
    main()
