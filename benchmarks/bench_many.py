"""Dataset throughput: several scans one at a time (``reconstruct``) against all at once
(``reconstruct_many``, one batched training loop), in scans per hour, with each scan's CD.

Scans: the z-facing open part of each bone in ``shared/data/bones`` (femur, pelvis, talus, tibia),
100,000 area samples each (mm); CD = ½(mean A→B + mean B→A) over ``--samples`` area samples.

    python benchmarks/bench_many.py --preset fast --bones femur,tibia,pelvis,talus
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_reconstruct import make_input  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="fast")
    p.add_argument("--bones", default="femur,tibia,pelvis,talus")
    p.add_argument("--device", default="auto")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--seed", type=int, default=42)
    p.add_argument("--samples", type=int, default=300_000)
    args = p.parse_args()
    import ultraboneudf
    from ultraboneudf.evaluation import evaluate

    names = args.bones.split(",")
    inputs = [make_input(n) for n in names]
    overrides = {"train.iters": args.iters} if args.iters else {}
    t0 = time.perf_counter()
    single = [ultraboneudf.reconstruct(pts, preset=args.preset, device=args.device, seed=args.seed, **overrides)
              for pts, _ in inputs]
    t_single = time.perf_counter() - t0
    t0 = time.perf_counter()
    many = ultraboneudf.reconstruct_many([pts for pts, _ in inputs], preset=args.preset, device=args.device,
                                         seed=args.seed, sources=names, **overrides)
    t_many = time.perf_counter() - t0

    def cd(rec, truth):
        return "no surface" if rec.mesh is None else f"{evaluate(rec.mesh, truth, samples=args.samples, seed=0).cd_mm:.3f}"

    print("| scan | CD one at a time (mm) | CD batched (mm) |\n|---|---|---|")
    for name, (_, truth), a, b in zip(names, inputs, single, many):
        print(f"| {name} | {cd(a, truth)} | {cd(b, truth)} |")
    k = len(names)
    print()
    print("| mode | wall time (s) | scans per hour | speed-up |\n|---|---|---|---|")
    print(f"| one at a time | {t_single:.1f} | {3600 * k / t_single:.0f} | 1.00 |")
    print(f"| {k} at once | {t_many:.1f} | {3600 * k / t_many:.0f} | {t_single / t_many:.2f} |")
    print(f"\ndevice {single[0].device}, preset {args.preset}, "
          f"{single[0].config.train.iters} steps × {single[0].config.train.batch} queries per scan")


if __name__ == "__main__":
    main()
