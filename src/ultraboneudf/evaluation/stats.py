"""Statistics of docs/ALGORITHMS.md §6.3: paired Wilcoxon signed-rank tests with Bonferroni correction,
per-specimen means and the mean of the specimen means (Tables 1–3).

Data model: one :class:`Record` per (method, specimen, reconstruction) with the metrics in mm;
``None`` metrics mark a failed reconstruction (no mesh), which is counted, never averaged as 0.

Conventions:

* Pairing unit: the individual reconstruction. A competitor is paired with the baseline on the key
  ``(specimen, reconstruction)``; pairs where either side failed are left out and counted.
* Test: two-sided Wilcoxon signed-rank on ``baseline − competitor``; zero differences are
  discarded before ranking (Wilcoxon's convention), ties share mean ranks. The exact null
  distribution is used when ``n ≤ 50`` and no ties remain, the normal approximation otherwise
  (``scipy.stats.wilcoxon``). The statistic is ``min(W+, W−)``.
* Bonferroni: ``p_corr = min(1, k · p_raw)`` with ``k`` the number of competitors (default: those
  present in the data).
* Table entries: the mean over a specimen's reconstructions, then the mean of those specimen
  means (not the mean over all reconstructions).

Results file (``ultraboneudf stats RESULTS``): CSV with a header row and columns ``method``,
``specimen``, ``reconstruction``, ``cd_mm``, ``hd95_mm`` (other columns are ignored; an empty
metric cell, ``nan`` or ``failed`` marks a failure).
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..io import atomic_write_bytes

METRICS = ("cd_mm", "hd95_mm")
CSV_COLUMNS = ("method", "specimen", "reconstruction", "cd_mm", "hd95_mm")


@dataclass(frozen=True)
class Record:
    """One reconstruction's metrics (mm); ``None`` = failed (no mesh)."""

    method: str
    specimen: str
    reconstruction: str
    cd_mm: Optional[float]
    hd95_mm: Optional[float]

    def value(self, metric: str) -> Optional[float]:
        if metric not in METRICS:
            raise InputError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
        return getattr(self, metric)

    @property
    def failed(self) -> bool:
        return self.cd_mm is None and self.hd95_mm is None


@dataclass(frozen=True)
class WilcoxonResult:
    """A paired two-sided Wilcoxon signed-rank test.

    ``n``: non-zero differences used; ``zeros``: zero differences discarded; ``statistic``:
    ``min(W+, W−)``; ``method``: ``"exact"`` or ``"approx"`` (normal approximation).
    """

    n: int
    zeros: int
    statistic: float
    p_raw: float
    method: str


@dataclass(frozen=True)
class Comparison:
    """Baseline against one competitor on one metric; ``p_corr = min(1, k · p_raw)``.

    ``baseline_better``/``competitor_better``: pairs in which that side has the lower value;
    ``missing``: reconstructions left out because one side failed or is absent;
    ``median_difference_mm``: median of ``baseline − competitor`` over the pairs.
    """

    baseline: str
    competitor: str
    metric: str
    n: int
    zeros: int
    statistic: float
    p_raw: float
    p_corr: float
    k: int
    method: str
    baseline_better: int
    competitor_better: int
    missing: int
    median_difference_mm: float

    def to_dict(self) -> dict:
        return asdict(self)


def wilcoxon_signed_rank(x: Sequence[float], y: Sequence[float]) -> WilcoxonResult:
    """Two-sided paired Wilcoxon signed-rank test of ``x`` against ``y`` (zero differences discarded).

    With no non-zero difference the test is undefined: ``statistic`` and ``p_raw`` are NaN.
    """
    from scipy.stats import wilcoxon  # scipy is a core dependency; imported here to keep import light

    d = np.asarray(x, dtype=np.float64) - np.asarray(y, dtype=np.float64)
    if d.ndim != 1:
        raise ValueError("wilcoxon_signed_rank: x and y must be 1-D and of equal length")
    if not np.all(np.isfinite(d)):
        raise ValueError("wilcoxon_signed_rank: values must be finite")
    nonzero = d[d != 0.0]
    zeros = int(len(d) - len(nonzero))
    if len(nonzero) == 0:
        return WilcoxonResult(n=0, zeros=zeros, statistic=math.nan, p_raw=math.nan, method="none")
    ties = len(np.unique(np.abs(nonzero))) < len(nonzero)
    method = "exact" if len(nonzero) <= 50 and not ties else "approx"
    res = wilcoxon(nonzero, alternative="two-sided", zero_method="wilcox", method=method)
    return WilcoxonResult(n=int(len(nonzero)), zeros=zeros, statistic=float(res.statistic),
                          p_raw=float(res.pvalue), method=method)


def bonferroni(p_raw: float, k: int) -> float:
    """``min(1, k · p_raw)``; NaN stays NaN."""
    return p_raw if math.isnan(p_raw) else min(1.0, k * p_raw)


def methods_in(records: Iterable[Record]) -> list[str]:
    """Method names in order of first appearance."""
    return list(dict.fromkeys(r.method for r in records))


def specimens_in(records: Iterable[Record]) -> list[str]:
    """Specimen names in order of first appearance."""
    return list(dict.fromkeys(r.specimen for r in records))


def _by_key(records: Iterable[Record], method: str, metric: str, source: str) -> dict[tuple[str, str], Optional[float]]:
    out: dict[tuple[str, str], Optional[float]] = {}
    for r in records:
        if r.method != method:
            continue
        key = (r.specimen, r.reconstruction)
        if key in out:
            raise InputError(f"{source}: method {method!r} has two rows for specimen {key[0]!r}, "
                             f"reconstruction {key[1]!r}")
        out[key] = r.value(metric)
    return out


def compare_to_baseline(records: Sequence[Record], baseline: str, metric: str = "cd_mm",
                        competitors: Optional[Sequence[str]] = None, k: Optional[int] = None,
                        source: str = "results") -> list[Comparison]:
    """Paired Wilcoxon tests of ``baseline`` against each competitor, Bonferroni-corrected.

    ``competitors`` defaults to every other method in ``records``; ``k`` to their number.
    """
    methods = methods_in(records)
    if baseline not in methods:
        raise InputError(f"{source}: baseline method {baseline!r} not found; methods: {', '.join(methods)}")
    competitors = [m for m in (competitors or methods) if m != baseline]
    for m in competitors:
        if m not in methods:
            raise InputError(f"{source}: method {m!r} not found; methods: {', '.join(methods)}")
    if not competitors:
        raise InputError(f"{source}: no competitor to compare {baseline!r} with")
    k = len(competitors) if k is None else int(k)
    if k < 1:
        raise InputError(f"Bonferroni factor k must be ≥ 1, got {k}")
    base = _by_key(records, baseline, metric, source)
    out = []
    for m in competitors:
        other = _by_key(records, m, metric, source)
        keys = sorted(set(base) | set(other))
        paired = [(base[key], other[key]) for key in keys
                  if base.get(key) is not None and other.get(key) is not None]
        x = np.array([p[0] for p in paired], dtype=np.float64)
        y = np.array([p[1] for p in paired], dtype=np.float64)
        test = wilcoxon_signed_rank(x, y)
        out.append(Comparison(
            baseline=baseline, competitor=m, metric=metric, n=test.n, zeros=test.zeros,
            statistic=test.statistic, p_raw=test.p_raw, p_corr=bonferroni(test.p_raw, k), k=k,
            method=test.method, baseline_better=int((x < y).sum()), competitor_better=int((x > y).sum()),
            missing=len(keys) - len(paired),
            median_difference_mm=float(np.median(x - y)) if len(x) else math.nan))
    return out


def specimen_means(records: Iterable[Record], metric: str = "cd_mm") -> dict[str, dict[str, float]]:
    """``{method: {specimen: mean over that specimen's successful reconstructions}}`` (mm)."""
    sums: dict[str, dict[str, list[float]]] = {}
    for r in records:
        v = r.value(metric)
        per = sums.setdefault(r.method, {})
        if v is not None:
            per.setdefault(r.specimen, []).append(v)
    return {m: {s: float(np.mean(v)) for s, v in per.items()} for m, per in sums.items()}


def mean_of_specimen_means(means: dict[str, float]) -> float:
    """The tables' "mean" column: the mean of the specimen means (NaN when there are none)."""
    return float(np.mean(list(means.values()))) if means else math.nan


def failure_counts(records: Iterable[Record]) -> dict[str, int]:
    """Failed reconstructions (no mesh) per method, every method listed."""
    out: dict[str, int] = {}
    for r in records:
        out[r.method] = out.get(r.method, 0) + int(r.failed)
    return out


# --------------------------------------------------------------------------------------------
# results files


def _parse_metric(text: str, path: Path, line: int, column: str) -> Optional[float]:
    s = (text or "").strip().lower()
    if s in ("", "nan", "none", "null", "failed", "fail", "-", "—"):
        return None
    try:
        v = float(s)
    except ValueError:
        raise InputError(f"{path}: line {line}: column {column}: not a number: {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise InputError(f"{path}: line {line}: column {column}: expected a distance ≥ 0 mm, got {text!r}")
    return v


def read_results_csv(path: str | os.PathLike) -> list[Record]:
    """Read a results CSV (see the module docstring); errors name the file and line."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a results CSV")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip().lower() for h in (reader.fieldnames or [])]
    missing = [c for c in ("method", "specimen", "reconstruction") if c not in header]
    if missing or not any(m in header for m in METRICS):
        raise InputError(f"{path}: expected a header with columns {', '.join(CSV_COLUMNS)}; "
                         f"found {', '.join(header) or 'nothing'}")
    reader.fieldnames = header
    records = []
    for i, row in enumerate(reader, start=2):
        if not any((v or "").strip() for v in row.values() if isinstance(v, str)):
            continue
        names = {c: (row.get(c) or "").strip() for c in ("method", "specimen", "reconstruction")}
        for c, v in names.items():
            if not v:
                raise InputError(f"{path}: line {i}: empty {c}")
        records.append(Record(
            cd_mm=_parse_metric(row.get("cd_mm", ""), path, i, "cd_mm") if "cd_mm" in header else None,
            hd95_mm=_parse_metric(row.get("hd95_mm", ""), path, i, "hd95_mm") if "hd95_mm" in header else None,
            **names))
    if not records:
        raise InputError(f"{path}: no result rows")
    return records


def write_results_csv(records: Iterable[Record], path: str | os.PathLike) -> None:
    """Write records in the format :func:`read_results_csv` reads (failures as empty cells), atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in records:
        w.writerow([r.method, r.specimen, r.reconstruction,
                    "" if r.cd_mm is None else repr(float(r.cd_mm)),
                    "" if r.hd95_mm is None else repr(float(r.hd95_mm))])
    atomic_write_bytes(path, buf.getvalue().encode("utf-8"))
