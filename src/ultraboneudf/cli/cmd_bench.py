"""``ultraboneudf bench dataset|run|report``: datasets as manifests, a resumable experiment runner,
and the paper's tables from its results (docs/bench.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..config import PRESETS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="datasets, a resumable experiment runner and the paper's tables",
                       description="Run the paper's experiments (E1, E3–E7 of docs/ALGORITHMS.md §6.4) or any "
                                   "grid of methods and --sweep values over a dataset manifest; every cell "
                                   "is a folder with mesh, sidecar and result, and a killed run resumes.")
    bench = p.add_subparsers(dest="bench_command", metavar="STEP", required=True)

    d = bench.add_parser("dataset", help="write a dataset and its manifest.csv")
    d.add_argument("kind", choices=["openbone", "closedbone", "simsweep", "pairs"])
    d.add_argument("source", type=Path, help="a folder of bone meshes (pairs: of NAME.<cloud> + NAME_gt.<mesh>)")
    d.add_argument("--out", type=Path, required=True)
    d.add_argument("--samples", type=int, default=100_000, help="points per open/closed bone")
    d.add_argument("--level", default="hard", help="simsweep: the simulator's noise level")
    d.add_argument("--seeds", default="0", help="simsweep: comma-separated seeds")
    d.add_argument("--quiet", action="store_true")
    d.set_defaults(func=run_dataset)

    r = bench.add_parser("run", help="run every unfinished cell of an experiment or grid")
    r.add_argument("experiment", nargs="?", default=None, help="E1, E3, E4, E5, E6 or E7 (or none: a grid)")
    r.add_argument("--dataset", type=Path, required=True, help="a manifest.csv")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--method", dest="methods", action="append", default=[], help="a method (repeatable)")
    r.add_argument("--sweep", dest="sweeps", action="append", default=[], metavar="KEY=V1,V2",
                   help="one grid axis (repeatable: the grid is every combination)")
    r.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    r.add_argument("--preset", default="robust", choices=list(PRESETS))
    r.add_argument("--seed", type=int, default=42)
    r.add_argument("--device", default="auto")
    r.add_argument("--samples", type=int, default=300_000, help="area samples per surface for CD/HD95")
    r.add_argument("--retry-failed", action="store_true", help="run the failed cells again")
    r.add_argument("--workers", type=int, default=1, help="cells run at once in a process pool (default 1)")
    r.add_argument("--engine", default="local", choices=["local", "ray"],
                   help="local (this machine) or ray (a Ray cluster: one CPU, or one GPU with --device "
                        "cuda, per cell; a cell whose worker dies is retried; needs "
                        "pip install 'ultraboneudf[ray]')")
    r.add_argument("--address", default=None,
                   help="--engine ray: the cluster's address, e.g. 10.0.0.5:6379 or auto (default: a "
                        "new local Ray instance); --out must be on storage every node sees")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=run_run)

    t = bench.add_parser("report", help="the CD and HD95 tables (and Wilcoxon tests) of a run folder")
    t.add_argument("folder", type=Path)
    t.add_argument("--format", default="md", choices=["md", "csv", "latex", "html"])
    t.add_argument("--baseline", default=None, help="a row label to test against every other (Wilcoxon)")
    t.add_argument("--html", type=Path, default=None, metavar="FILE",
                   help="also write the whole report as one HTML page that opens offline: the tables, "
                        "the CD against a swept setting (e.g. E4's network depth) and each unit's "
                        "meshes coloured by their distance to the truth")
    t.set_defaults(func=run_report)


def run_dataset(args: argparse.Namespace) -> int:
    from ..bench.datasets import make_dataset
    from ..errors import InputError
    from ..progress import Progress

    try:
        seeds = tuple(int(s) for s in args.seeds.split(","))
    except ValueError:
        raise InputError(f"--seeds expects comma-separated integers, got {args.seeds!r}") from None
    manifest = make_dataset(args.kind, args.source, args.out, samples=args.samples, level=args.level,
                            seeds=seeds, progress=Progress(quiet=args.quiet))
    print(f"bench: wrote {manifest}")
    return 0


def run_run(args: argparse.Namespace) -> int:
    from ..bench.manifest import read_manifest
    from ..bench.runner import plan, run_cells
    from ..progress import Progress

    cells = plan(read_manifest(args.dataset), args.experiment, args.methods, args.sweeps, args.sets,
                 args.preset, args.seed)
    counts = run_cells(cells, args.out, device=args.device, samples=args.samples,
                       retry_failed=args.retry_failed, workers=args.workers, progress=Progress(quiet=args.quiet),
                       engine=args.engine, address=args.address)
    print(f"bench: {counts['done']} cells done, {counts['failed']} failed, {counts['skipped']} finished "
          f"before; results in {args.out / 'results.csv'} and {args.out / 'results.sqlite'}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    from ..bench.report import html_report, report
    from ..io import atomic_write_bytes

    sys.stdout.write(report(args.folder, args.format, args.baseline))
    if args.html is not None:
        atomic_write_bytes(args.html, html_report(args.folder, args.baseline).encode("utf-8"))
        print(f"bench report: wrote {args.html}", file=sys.stderr)
    return 0
