"""The paper's tables from a runner's folder: per-specimen CD and HD95 with the best in bold and
the mean of specimen means (§6.1), and the paired Wilcoxon tests with Bonferroni correction (§6.3)."""

from __future__ import annotations

import re
from pathlib import Path

from ..errors import InputError
from ..evaluation.stats import Record, compare_to_baseline
from ..evaluation.tables import Table, comparisons_table, format_table, results_table
from .runner import finished_rows


def labels(rows: list[dict]) -> list[str]:
    """What each table row is called: the method, and those of its overrides that are not the same
    in every cell (the grid's axes)."""
    common = set.intersection(*(set((r.get("overrides") or "").split()) for r in rows))
    out = []
    for r in rows:
        own = [o for o in (r.get("overrides") or "").split() if o not in common]
        out.append(r["method"] + (f" [{' '.join(own)}]" if own else ""))
    return out


def _natural(text: str) -> list:
    """Sort key that orders the numbers inside a label by value (σ = 0, 0.5, 1.0, 1.5, 2.0, 10)."""
    parts = re.split(r"(-?\d+(?:\.\d+)?(?:e-?\d+)?)", text)
    return [(0, float(p), "") if i % 2 else (1, 0.0, p) for i, p in enumerate(parts)]


def records(out: Path) -> list[Record]:
    """One :class:`Record` per finished cell (failures as ``None``)."""
    rows = finished_rows(out)
    if not rows:
        raise InputError(f"{out}: no finished cells (run `ultraboneudf bench run` first)")
    return [Record(method=name, specimen=r["specimen"], reconstruction=r["unit"],
                   cd_mm=r["cd_mm"] if r["status"] == "ok" else None,
                   hd95_mm=r["hd95_mm"] if r["status"] == "ok" else None) for r, name in zip(rows, labels(rows))]


def report(out: Path, fmt: str = "md", baseline: str | None = None, decimals: int = 2) -> str:
    """The CD and HD95 tables (and, with ``baseline``, its Wilcoxon tests against every other
    method, Bonferroni over their number) in ``fmt`` (``md``, ``csv``, ``latex``)."""
    recs = records(out)
    rows = sorted({r.method for r in recs}, key=_natural)
    parts = []
    for metric in ("cd_mm", "hd95_mm"):
        parts.append(format_table(results_table(recs, metric, methods=rows, decimals=decimals), fmt))
    parts.append(format_table(cost_table(out, rows), fmt))
    if baseline is not None:
        for metric in ("cd_mm", "hd95_mm"):
            comps = compare_to_baseline(recs, baseline, metric, source=str(out))
            parts.append(format_table(comparisons_table(comps), fmt, first_header="competitor"))
    return "\n\n".join(parts) + "\n"


def cost_table(out: Path, order: list[str] | None = None) -> Table:
    """Table 4 of the paper (experiment E2): per row label, the trainable parameters and the mean
    seconds of training and of the whole reconstruction over its finished cells (failures included:
    they cost time too)."""
    import statistics

    rows = finished_rows(out)
    groups: dict[str, list[dict]] = {}
    for r, name in zip(rows, labels(rows)):
        groups.setdefault(name, []).append(r)
    mean = lambda vals: statistics.fmean(vals) if vals else None  # noqa: E731
    table_rows = []
    for name in order or sorted(groups, key=_natural):
        g = groups.get(name, [])
        params = [r["parameters"] for r in g if r.get("parameters") is not None]
        table_rows.append((name, [mean(params), mean([r["train_s"] for r in g if r.get("train_s") is not None]),
                                  mean([r["total_s"] for r in g if r.get("total_s") is not None]), float(len(g))]))
    return Table(title="Parameters and runtime (s, mean per reconstruction)",
                 columns=["parameters", "train s", "total s", "cells"], rows=table_rows,
                 bold=[[False] * 4 for _ in table_rows], decimals=1, integer_columns=(0, 3))
