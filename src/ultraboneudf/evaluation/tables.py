"""Tables like the paper's (Tables 1–3): methods × specimens + mean, best value in bold.

A cell is the mean over that specimen's successful reconstructions (mm); "mean" is the mean of the
specimen means (docs/ALGORITHMS.md §6.1). Lower is better for every metric here, so the bold cell of a
column is its minimum, compared at the printed precision (visible ties are all bold). A ``failed``
column is added when any reconstruction failed. Output: Markdown, CSV (plain numbers, no bold),
LaTeX (booktabs) and HTML (a ``<table>`` for a report page).
"""

from __future__ import annotations

import csv
import html
import io
import math
from dataclasses import dataclass
from typing import Optional, Sequence

from .stats import (
    Comparison,
    Record,
    failure_counts,
    mean_of_specimen_means,
    methods_in,
    specimen_means,
    specimens_in,
)

FORMATS = ("md", "csv", "latex", "html")
METRIC_LABELS = {"cd_mm": "CD (mm)", "hd95_mm": "HD95 (mm)"}


@dataclass(frozen=True)
class Table:
    """A rendered-agnostic table: ``rows[i] = (label, cells)``, ``bold[i][j]`` marks best cells."""

    title: str
    columns: list[str]
    rows: list[tuple[str, list[Optional[float]]]]
    bold: list[list[bool]]
    decimals: int = 2
    integer_columns: tuple[int, ...] = ()

    def cell_text(self, i: int, j: int) -> str:
        v = self.rows[i][1][j]
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return "—"
        if j in self.integer_columns:
            return str(int(v))
        return f"{v:.{self.decimals}f}"


def results_table(records: Sequence[Record], metric: str = "cd_mm", methods: Optional[Sequence[str]] = None,
                  specimens: Optional[Sequence[str]] = None, decimals: int = 2) -> Table:
    """Methods (rows) × specimens + mean (columns) of ``metric``, best per column in bold."""
    methods = list(methods or methods_in(records))
    specimens = list(specimens or specimens_in(records))
    means = specimen_means(records, metric)
    failures = failure_counts(records)
    with_fail = any(failures.get(m, 0) for m in methods)
    rows = []
    for m in methods:
        per = means.get(m, {})
        cells: list[Optional[float]] = [per.get(s) for s in specimens]
        cells.append(mean_of_specimen_means(per) if per else None)
        if with_fail:
            cells.append(float(failures.get(m, 0)))
        rows.append((m, cells))
    n_value_cols = len(specimens) + 1
    bold = [[False] * len(r[1]) for r in rows]
    for j in range(n_value_cols):
        vals = [round(r[1][j], decimals) for r in rows if r[1][j] is not None and not math.isnan(r[1][j])]
        if not vals or len(rows) < 2:
            continue
        best = min(vals)
        for i, r in enumerate(rows):
            v = r[1][j]
            bold[i][j] = v is not None and not math.isnan(v) and round(v, decimals) == best
    columns = [str(s) for s in specimens] + ["mean"] + (["failed"] if with_fail else [])
    return Table(title=METRIC_LABELS.get(metric, metric), columns=columns, rows=rows, bold=bold,
                 decimals=decimals, integer_columns=(n_value_cols,) if with_fail else ())


def comparisons_table(comparisons: Sequence[Comparison], decimals: int = 4) -> Table:
    """One row per competitor: n, statistic, p_raw, p_corr (and who wins how often)."""
    rows = []
    for c in comparisons:
        rows.append((c.competitor, [float(c.n), c.statistic, c.p_raw, c.p_corr,
                                    float(c.baseline_better), float(c.competitor_better), float(c.missing)]))
    title = (f"Wilcoxon signed-rank, {comparisons[0].baseline} vs competitors, "
             f"{METRIC_LABELS.get(comparisons[0].metric, comparisons[0].metric)}, "
             f"Bonferroni k = {comparisons[0].k}") if comparisons else "Wilcoxon signed-rank"
    return Table(title=title,
                 columns=["n", "statistic", "p_raw", "p_corr", "baseline better", "competitor better", "missing"],
                 rows=rows, bold=[[False] * 7 for _ in rows], decimals=decimals,
                 integer_columns=(0, 4, 5, 6))


def _p_text(v: float, decimals: int) -> str:
    if math.isnan(v):
        return "—"
    return f"{v:.{decimals}f}" if v >= 10 ** (-decimals) else f"{v:.1e}"


def to_markdown(table: Table, first_header: str = "method") -> str:
    """GitHub-flavoured Markdown, best cells as ``**x**``."""
    head = "| " + " | ".join([first_header] + table.columns) + " |"
    sep = "| --- |" + " ---: |" * len(table.columns)
    lines = [f"**{table.title}**", "", head, sep]
    for i, (label, cells) in enumerate(table.rows):
        texts = []
        for j in range(len(cells)):
            t = _text(table, i, j)
            texts.append(f"**{t}**" if table.bold[i][j] else t)
        lines.append("| " + " | ".join([label] + texts) + " |")
    return "\n".join(lines) + "\n"


def to_html(table: Table, first_header: str = "method") -> str:
    """An HTML ``<table>`` with its title as caption, best cells in ``<b>``."""
    esc = html.escape
    head = "".join(f"<th>{esc(c)}</th>" for c in [first_header] + table.columns)
    body = []
    for i, (label, cells) in enumerate(table.rows):
        texts = [f"<b>{esc(_text(table, i, j))}</b>" if table.bold[i][j] else esc(_text(table, i, j))
                 for j in range(len(cells))]
        body.append(f"<tr><th>{esc(label)}</th>" + "".join(f"<td>{t}</td>" for t in texts) + "</tr>")
    return (f"<table>\n<caption>{esc(table.title)}</caption>\n<tr>{head}</tr>\n" + "\n".join(body)
            + "\n</table>\n")


def to_csv(table: Table, first_header: str = "method") -> str:
    """Plain CSV with full-precision numbers (empty cell = no value)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([first_header] + table.columns)
    for label, cells in table.rows:
        w.writerow([label] + ["" if v is None or (isinstance(v, float) and math.isnan(v)) else
                              (str(int(v)) if j in table.integer_columns else repr(float(v)))
                              for j, v in enumerate(cells)])
    return buf.getvalue()


def _latex_escape(s: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("$", r"\$"), ("#", r"\#"),
                 ("_", r"\_"), ("{", r"\{"), ("}", r"\}"), ("~", r"\textasciitilde{}"), ("^", r"\^{}")):
        s = s.replace(a, b)
    return s


def to_latex(table: Table, first_header: str = "method") -> str:
    """A booktabs ``tabular`` (needs ``\\usepackage{booktabs}``), best cells in ``\\textbf``."""
    cols = "l" + "r" * len(table.columns)
    lines = [f"% {table.title}", f"\\begin{{tabular}}{{{cols}}}", "\\toprule",
             " & ".join(_latex_escape(c) for c in [first_header] + table.columns) + " \\\\", "\\midrule"]
    for i, (label, cells) in enumerate(table.rows):
        texts = []
        for j in range(len(cells)):
            t = _latex_escape(_text(table, i, j)).replace("—", "--")
            texts.append(f"\\textbf{{{t}}}" if table.bold[i][j] else t)
        lines.append(" & ".join([_latex_escape(label)] + texts) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(lines) + "\n"


def _text(table: Table, i: int, j: int) -> str:
    col = table.columns[j]
    v = table.rows[i][1][j]
    if col in ("p_raw", "p_corr") and v is not None:
        return _p_text(v, table.decimals)
    if col == "statistic" and v is not None and not math.isnan(v):
        return f"{v:g}"
    return table.cell_text(i, j)


def format_table(table: Table, fmt: str = "md", first_header: str = "method") -> str:
    """Render ``table`` as ``md``, ``csv``, ``latex`` or ``html``."""
    if fmt == "md":
        return to_markdown(table, first_header)
    if fmt == "csv":
        return to_csv(table, first_header)
    if fmt == "latex":
        return to_latex(table, first_header)
    if fmt == "html":
        return to_html(table, first_header)
    raise ValueError(f"unknown table format {fmt!r}; use one of {', '.join(FORMATS)}")
