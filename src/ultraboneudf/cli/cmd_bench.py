"""``ultraboneudf bench dataset|run|report``: datasets as manifests, a resumable experiment runner,
and the paper's tables from its results (docs/bench.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..config import PRESETS
from . import add_overwrite


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="datasets, a resumable experiment runner and the paper's tables",
                       description="Run the paper's experiments (E1, E3–E7 of docs/ALGORITHMS.md §6.4) or any "
                                   "grid of methods and --sweep values over a dataset manifest; every cell "
                                   "is a folder with mesh, sidecar and result, and a killed run resumes.")
    bench = p.add_subparsers(dest="bench_command", metavar="STEP", required=True)

    d = bench.add_parser("dataset", help="write a dataset and its manifest.csv")
    d.add_argument("kind", choices=["openbone", "closedbone", "simsweep", "pairs"])
    d.add_argument("source", type=Path, help="a folder of bone meshes (pairs: of NAME.<cloud> + NAME_gt.<mesh>)")
    d.add_argument("--out", type=Path, required=True,
                   help="a new folder (or an earlier dataset's, replaced as a whole)")
    d.add_argument("--samples", type=int, default=100_000, help="points per open/closed bone")
    d.add_argument("--level", default="hard", help="simsweep: the simulator's noise level")
    d.add_argument("--seeds", default="0", help="simsweep: comma-separated seeds")
    d.add_argument("--quiet", action="store_true")
    add_overwrite(d, "the --out folder as a whole")
    d.set_defaults(func=run_dataset)

    r = bench.add_parser("run", help="run every unfinished cell of an experiment or grid")
    r.add_argument("experiment", nargs="?", default=None, help="E1, E3, E4, E5, E6 or E7 (or none: a grid)")
    r.add_argument("--dataset", type=Path, required=True, help="a manifest.csv")
    r.add_argument("--out", type=Path, required=True,
                   help="a new folder, or one of an earlier run (its finished cells are kept)")
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
                        "meshes coloured by their distance to the truth (and beside it the sidecar "
                        "FILE.json)")
    add_overwrite(t, "FILE and its sidecar")
    t.set_defaults(func=run_report)


def run_dataset(args: argparse.Namespace) -> int:
    from ..errors import InputError
    from ..io import check_input, check_output

    check_output(args.out, inputs=(args.source,), overwrite=args.overwrite, kind="folder")
    try:
        seeds = tuple(int(s) for s in args.seeds.split(","))
    except ValueError:
        raise InputError(f"--seeds expects comma-separated integers, got {args.seeds!r}") from None
    if args.samples < 100:
        raise InputError(f"--samples: at least 100 points per bone, got {args.samples}")
    check_input(args.source, "folder", folder=True)
    from ..bench.datasets import make_dataset
    from ..io import record, write_folder_output
    from ..progress import Progress

    def fill(folder: Path) -> Path:
        return make_dataset(args.kind, args.source, folder, samples=args.samples, level=args.level,
                            seeds=seeds, progress=Progress(quiet=args.quiet))

    write_folder_output(args.out, fill, record("bench dataset", kind=args.kind, source=str(args.source.resolve())),
                        overwrite=args.overwrite)
    print(f"bench: wrote {args.out / 'manifest.csv'}")
    return 0


def run_run(args: argparse.Namespace) -> int:
    from ..bench.manifest import read_manifest
    from ..bench.runner import plan
    from ..errors import InputError
    from ..io import check_output

    if args.workers < 1 or args.samples < 1:
        raise InputError(f"--workers and --samples must be at least 1, got {args.workers} and {args.samples}")
    from ..bench.runner import earlier_run

    if not earlier_run(args.out):
        check_output(args.out, inputs=(args.dataset,), kind="run")
    cells = plan(read_manifest(args.dataset), args.experiment, args.methods, args.sweeps, args.sets,
                 args.preset, args.seed)
    from ..bench.runner import run_cells
    from ..progress import Progress

    counts = run_cells(cells, args.out, device=args.device, samples=args.samples,
                       retry_failed=args.retry_failed, workers=args.workers, progress=Progress(quiet=args.quiet),
                       engine=args.engine, address=args.address)
    print(f"bench: {counts['done']} cells done, {counts['failed']} failed, {counts['skipped']} finished "
          f"before; results in {args.out / 'results.csv'} and {args.out / 'results.sqlite'}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    from ..io import check_input, check_output, record, write_output

    if args.html is not None:
        check_output(args.html, overwrite=args.overwrite)
    check_input(args.folder, "folder", folder=True)
    from ..bench.report import html_report, report

    sys.stdout.write(report(args.folder, args.format, args.baseline))
    if args.html is not None:
        write_output(args.html, html_report(args.folder, args.baseline).encode("utf-8"),
                     record("bench report", folder=str(args.folder.resolve()), baseline=args.baseline),
                     overwrite=args.overwrite)
        print(f"bench report: wrote {args.html}", file=sys.stderr)
    return 0
