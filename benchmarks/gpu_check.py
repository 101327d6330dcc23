"""The GPU check, in one call: what a session with a GPU should measure, ready to run.

    python benchmarks/gpu_check.py --out gpu_check_out            # on the GPU machine (CUDA)
    python benchmarks/gpu_check.py --quick --out /tmp/check       # on a CPU, tiny budgets: that it works

1. ``official`` and the default preset on the open femur (the input of the tests and the README,
   100,000 points), on CUDA: seconds per stage, iterations per second, peak GPU memory, CD and HD95
   (``benchmarks/bench_reconstruct.py``, one process per run);
2. E1 on one bone (``bench dataset openbone`` over the femur, ``bench run E1``): every method of the
   paper's Table 1 at the default preset, and the CD/HD95 table (``bench report``).

Everything goes to ``--out``: ``reconstruct.json`` (the rows of step 1), ``e1/`` (the runner's
folder, ``results.csv``) and ``report.md``. ``--quick`` runs the same steps on the CPU with a few
steps of training, the demo phantom for step 1 and small evaluations, so the test suite can check
that the script works; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BONES = Path(os.environ.get("ULTRABONEUDF_BONES", HERE.parents[1] / "shared/data/bones"))


def _run(cmd: list[str]) -> None:
    print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--quick", action="store_true", help="CPU, tiny budgets: check that the script works")
    p.add_argument("--bone", default="femur", help="the bone of ../shared/data/bones for both steps")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    device = "cpu" if args.quick else "cuda"
    py = sys.executable
    t0 = time.perf_counter()

    quick_rec = (["--input", "phantom", "--iters", "30", "--samples", "20000", "--set", "extract.max_depth=6"]
                 if args.quick else ["--input", args.bone])
    _run([py, str(HERE / "bench_reconstruct.py"), "--presets", "official,robust", "--devices", device,
          "--json", str(args.out / "reconstruct.json"), *quick_rec])

    bones = args.out / "bones"
    bones.mkdir(exist_ok=True)
    link = bones / f"{args.bone}.ply"
    if not link.exists():
        link.symlink_to(BONES / f"{args.bone}.ply")
    cli = [py, "-m", "ultraboneudf.cli", "bench"]
    _run([*cli, "dataset", "openbone", str(bones), "--out", str(args.out / "data"), "--quiet",
          *(["--samples", "3000"] if args.quick else [])])
    quick_e1 = (["--set", "train.iters=20", "--set", "extract.max_depth=6", "--set", "grid.resolution=32",
                 "--samples", "5000"] if args.quick else [])
    _run([*cli, "run", "E1", "--dataset", str(args.out / "data" / "manifest.csv"), "--out", str(args.out / "e1"),
          "--device", device, "--quiet", *quick_e1])
    report = subprocess.run([*cli, "report", str(args.out / "e1")], check=True, capture_output=True, text=True).stdout
    (args.out / "report.md").write_text(report)
    rows = json.loads((args.out / "reconstruct.json").read_text())
    print(f"gpu_check: {len(rows)} reconstruction rows, E1 table in {args.out / 'report.md'}, "
          f"{time.perf_counter() - t0:.0f} s in all", file=sys.stderr)
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
