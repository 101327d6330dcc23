"""Frame registration on simulated sweeps: the frames' error along the surface normal, as tracked
and after ``align_frames``, measured against the simulator's true poses.

For each bone of ``../shared/data/bones`` (or ``ULTRABONEUDF_BONES``) and seed, ``ultraboneudf
simulate`` at a noise level (default ``hard``: tracking error 0.3 mm / 0.3° per frame), the
predicted masks compounded with the recorded poses (as ``reconstruct SWEEP`` does, before the
registration). Each point's tracking error is its position minus where the same pixel lies under
the true pose; its component along the true surface normal (the normal of the nearest of 2,000,000
area samples of the visible truth), with the sweep's common offset removed, is what a slice offset
is. Columns: mean absolute value of that error (mm) as tracked and registered, frames moved,
seconds of the registration.

    python benchmarks/bench_align.py --seeds 0,1,2
    python benchmarks/bench_align.py --bones talus --level moderate
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_reconstruct import BONES  # noqa: E402


def normal_errors(bone: str, level: str, seed: int) -> dict:
    import trimesh
    from scipy.spatial import cKDTree

    from ultraboneudf import load_mesh
    from ultraboneudf.sweep import align_frames, sweep_to_points
    from ultraboneudf.synth.simulator import config_with_noise, simulate_sweep

    sim = simulate_sweep(load_mesh(BONES / f"{bone}.ply"), config_with_noise(level, seed=seed))
    cp = sweep_to_points(sim.sweep, segment="masks")
    true = sim.true_positions(cp.frame_index, cp.pixel)
    samples, faces = trimesh.sample.sample_surface(sim.visible_mesh, 2_000_000, seed=0)
    _, nearest = cKDTree(samples).query(true, workers=-1)
    normal = sim.visible_mesh.face_normals[faces[nearest]]

    def error(points: np.ndarray) -> float:
        e = np.einsum("ij,ij->i", points - true, normal)
        return float(np.abs(e - e.mean()).mean())

    t0 = time.perf_counter()
    aligned, report = align_frames(cp)
    return {"bone": bone, "seed": seed, "points": len(cp), "frames": report.frames,
            "moved": report.aligned, "tracked_mm": error(cp.points), "registered_mm": error(aligned.points),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bones", default="femur,pelvis,talus,tibia")
    p.add_argument("--seeds", default="0")
    p.add_argument("--level", default="hard", help="the simulator's noise level")
    args = p.parse_args()
    print("| bone | seed | points | frames moved | error as tracked mm | registered mm | ratio | time s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for bone in args.bones.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            r = normal_errors(bone, args.level, seed)
            print(f"| {bone} | {seed} | {r['points']} | {r['moved']} / {r['frames']} | {r['tracked_mm']:.3f} | "
                  f"{r['registered_mm']:.3f} | {r['registered_mm'] / r['tracked_mm']:.2f} | {r['seconds']:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
