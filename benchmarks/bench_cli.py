"""How fast the command line answers before any work: ``--help``, ``--version``, a command's help,
a usage error, and refusals of a bad input, option, output or checkpoint, each the median of
``--repeat`` runs in a fresh process (seconds) and its peak resident memory (MB).

    python benchmarks/bench_cli.py [--repeat 5] [--src path/to/src]

None of these imports PyTorch, and a refusal of a point cloud, an option or an output imports no
trimesh either; a reconstruction's own start-up (importing torch) comes after every check.
``--src`` times another checkout's package (the same cases; the files they need are made here).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CASES = [
    ("ultraboneudf --help", ["--help"]),
    ("ultraboneudf --version", ["--version"]),
    ("ultraboneudf reconstruct --help", ["reconstruct", "--help"]),
    ("ultraboneudf simulate --help", ["simulate", "--help"]),
    ("ultraboneudf reconstruct x.xyz -o y.ply --seed -1 (usage error)", ["reconstruct", "x.xyz", "-o", "y.ply",
                                                                     "--seed", "-1"]),
    ("reconstruct nothing.xyz -o o.ply (no such file)", ["reconstruct", "nothing.xyz", "-o", "o.ply"]),
    ("reconstruct in.xyz -o o.ply --set train.nope=1 (unknown key)", ["reconstruct", "in.xyz", "-o", "o.ply", "--set",
                                                                    "train.nope=1"]),
    ("reconstruct in.xyz -o mine.ply (a user's file)", ["reconstruct", "in.xyz", "-o", "mine.ply"]),
    ("reconstruct in.xyz -o o.ply --checkpoint-every 10 --resume (not a checkpoint)",
     ["reconstruct", "in.xyz", "-o", "o.ply", "--checkpoint-every", "10", "--resume"]),
    ("reconstruct m.xyz -o o.ply (a cloud in metres)", ["reconstruct", "m.xyz", "-o", "o.ply"]),
    ("simulate in.xyz -o s --set n_frames=-3", ["simulate", "in.xyz", "-o", "s", "--set", "n_frames=-3"]),
]


def _files(folder: Path) -> None:
    import numpy as np

    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0, 40, (3000, 2)), rng.normal(0, 0.1, 3000)]
    np.savetxt(folder / "in.xyz", pts)
    np.savetxt(folder / "m.xyz", pts / 1000)
    (folder / "mine.ply").write_text("the user's mesh\n")
    (folder / "o.ply.ckpt").write_text("the user's notes\n")


def _once(argv: list[str], cwd: Path, env: dict) -> tuple[float, float, int]:
    """Seconds, peak resident MB and exit code of one run in a fresh process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "ultraboneudf.cli", *argv], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    return time.perf_counter() - t0, usage.ru_maxrss / 1024, os.waitstatus_to_exitcode(status)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--src", type=Path, default=Path(__file__).resolve().parents[1] / "src")
    args = p.parse_args()
    env = {**os.environ, "PYTHONPATH": str(args.src.resolve())}
    print("| command | median s | max s | peak MB | exit |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        _files(cwd)
        for label, argv in CASES:
            runs = [_once(argv, cwd, env) for _ in range(args.repeat)]
            times = [r[0] for r in runs]
            print(f"| `{label}` | {statistics.median(times):.2f} | {max(times):.2f} | "
                  f"{statistics.median(r[1] for r in runs):.0f} | {runs[-1][2]} |")


if __name__ == "__main__":
    main()
