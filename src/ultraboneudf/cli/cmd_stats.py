"""``ultraboneudf stats RESULTS --baseline M``: Wilcoxon + Bonferroni and paper-style tables."""

from __future__ import annotations

import argparse

from ..errors import InputError
from . import add_overwrite


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "stats", help="Wilcoxon signed-rank tests (Bonferroni) and per-specimen tables from a results CSV",
        description="RESULTS is a CSV with a header and the columns method, specimen, reconstruction, "
                    "cd_mm, hd95_mm (one row per reconstruction; an empty metric marks a failed "
                    "reconstruction). Prints, per metric, the table methods × specimens + mean (cells: "
                    "mean over the specimen's reconstructions; mean: mean of the specimen means; best in "
                    "bold) and paired two-sided Wilcoxon signed-rank tests of the baseline against each "
                    "other method, paired by reconstruction, zero differences discarded, with "
                    "p_corr = min(1, k·p_raw) (docs/ALGORITHMS.md §6.3).")
    p.add_argument("results", metavar="RESULTS", help="results CSV")
    p.add_argument("--baseline", required=True, metavar="M", help="the method tested against every other one")
    p.add_argument("--metric", default="both", choices=["cd_mm", "hd95_mm", "both"], help="default: both")
    p.add_argument("--methods", metavar="A,B,…", help="methods and their order (default: as in the file)")
    p.add_argument("--test", default="wilcoxon", choices=["wilcoxon"], help="paired test (only wilcoxon)")
    p.add_argument("--correction", default="bonferroni", choices=["bonferroni", "none"],
                   help="multiple-comparison correction (default bonferroni)")
    p.add_argument("--k", type=int, default=None, help="Bonferroni factor (default: number of competitors)")
    p.add_argument("--format", default="md", choices=["md", "csv", "latex"], help="table format (default md)")
    p.add_argument("--decimals", type=int, default=2, help="decimals of the mm tables (default 2)")
    p.add_argument("-o", "--out", metavar="FILE", help="write the tables to FILE instead of stdout (and "
                                                       "beside it the sidecar FILE.json)")
    add_overwrite(p, "FILE and its sidecar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..io import check_input, check_output, record, sha256_file, write_output

    if args.out:
        check_output(args.out, inputs=[args.results], overwrite=args.overwrite)
    check_input(args.results, "file")
    if args.decimals < 0 or args.decimals > 12:
        raise InputError(f"--decimals: between 0 and 12, got {args.decimals}")
    from ..evaluation.stats import compare_to_baseline, read_results_csv
    from ..evaluation.tables import comparisons_table, format_table, results_table

    records = read_results_csv(args.results)
    methods = [m.strip() for m in args.methods.split(",")] if args.methods else None
    metrics = ["cd_mm", "hd95_mm"] if args.metric == "both" else [args.metric]
    if args.k is not None and args.k < 1:
        raise InputError(f"--k: must be ≥ 1, got {args.k}")
    k = 1 if args.correction == "none" else args.k
    competitors = [m for m in methods if m != args.baseline] if methods else None
    parts = []
    for metric in metrics:
        if all(r.value(metric) is None for r in records):
            continue
        table = results_table(records, metric, methods=methods, decimals=args.decimals)
        comps = compare_to_baseline(records, args.baseline, metric, competitors=competitors, k=k,
                                    source=str(args.results))
        for t, header in ((table, "method"), (comparisons_table(comps), "competitor")):
            text = format_table(t, args.format, header)
            if args.format == "csv":
                text = f"# {t.title}\n{text}"
            parts.append(text)
    if not parts:
        raise InputError(f"{args.results}: no metric values (all reconstructions failed?)")
    output = "\n".join(parts)
    if args.out:
        meta = record("stats", inputs={str(args.results): sha256_file(args.results)},
                      options={k: str(v) for k, v in sorted(vars(args).items()) if k not in ("func", "out")})
        write_output(args.out, output.encode("utf-8"), meta, overwrite=args.overwrite)
        print(args.out)
    else:
        print(output, end="")
    return 0
