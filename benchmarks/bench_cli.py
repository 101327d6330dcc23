"""How fast the command line answers before any work: ``--help``, ``--version``, a command's help
and a usage error, each the median of ``--repeat`` runs in a fresh process (seconds).

    python benchmarks/bench_cli.py [--repeat 5]

These commands import neither PyTorch nor the geometry stack; a reconstruction's own start-up
(importing torch) comes after its arguments are checked.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

CASES = [
    ("ultraboneudf --help", ["--help"]),
    ("ultraboneudf --version", ["--version"]),
    ("ultraboneudf reconstruct --help", ["reconstruct", "--help"]),
    ("ultraboneudf simulate --help", ["simulate", "--help"]),
    ("ultraboneudf reconstruct x.xyz -o y.ply --seed -1 (usage error)", ["reconstruct", "x.xyz", "-o", "y.ply",
                                                                     "--seed", "-1"]),
]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args()
    print("| command | median s | max s | exit |")
    print("|---|---|---|---|")
    for label, argv in CASES:
        times, code = [], None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            code = subprocess.run([sys.executable, "-m", "ultraboneudf.cli", *argv], capture_output=True).returncode
            times.append(time.perf_counter() - t0)
        print(f"| `{label}` | {statistics.median(times):.2f} | {max(times):.2f} | {code} |")


if __name__ == "__main__":
    main()
