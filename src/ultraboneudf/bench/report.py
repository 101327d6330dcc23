"""The paper's tables from a runner's folder: per-specimen CD and HD95 with the best in bold and
the mean of specimen means (§6.1), and the paired Wilcoxon tests with Bonferroni correction (§6.3);
as one HTML page that opens offline, with the CD plotted against a swept setting (Fig. 10: the
network depth of E4) and, per unit, the methods' meshes coloured by their distance to the truth."""

from __future__ import annotations

import base64
import html
import re
import statistics
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
    method, Bonferroni over their number) in ``fmt`` (``md``, ``csv``, ``latex``, ``html``)."""
    tables = _tables(out, baseline, decimals)
    return "\n\n".join(format_table(t, fmt, first_header=h) for t, h in tables) + "\n"


def _tables(out: Path, baseline: str | None, decimals: int) -> list[tuple[Table, str]]:
    """The report's tables with the header of their first column."""
    recs = records(out)
    rows = sorted({r.method for r in recs}, key=_natural)
    tables = [(results_table(recs, metric, methods=rows, decimals=decimals), "method")
              for metric in ("cd_mm", "hd95_mm")]
    tables.append((cost_table(out, rows), "method"))
    if baseline is not None:
        for metric in ("cd_mm", "hd95_mm"):
            comps = compare_to_baseline(recs, baseline, metric, source=str(out))
            tables.append((comparisons_table(comps), "competitor"))
    return tables


def swept_axis(rows: list[dict]) -> tuple[str, dict[str, list[tuple[float, float]]]] | None:
    """The one numeric setting that differs between the cells (e.g. ``model.depth`` of E4)
    and, per series (the method with its other differing settings), the mean CD (mm) of its ok
    cells at each value, sorted by value; ``None`` unless exactly one such setting exists."""
    def settings(r: dict) -> dict[str, str]:
        return dict(o.split("=", 1) for o in (r.get("overrides") or "").split() if "=" in o)

    every = [settings(r) for r in rows]
    keys = sorted({k for s in every for k in s})
    varying = [k for k in keys if len({s.get(k) for s in every}) > 1]

    def number(text: str | None) -> float | None:
        try:
            return float(text) if text is not None else None
        except ValueError:
            return None

    axes = [k for k in varying if all(number(s.get(k)) is not None for s in every)]
    if len(axes) != 1:
        return None
    axis = axes[0]
    groups: dict[str, dict[float, list[float]]] = {}
    for r, s in zip(rows, every):
        rest = " ".join(f"{k}={s[k]}" for k in varying if k != axis and k in s)
        name = r["method"] + (f" [{rest}]" if rest else "")
        if r.get("status") == "ok" and r.get("cd_mm") is not None:
            groups.setdefault(name, {}).setdefault(float(s[axis]), []).append(r["cd_mm"])
    series = {name: sorted((x, statistics.fmean(v)) for x, v in by_x.items())
              for name, by_x in sorted(groups.items(), key=lambda kv: _natural(kv[0]))}
    return (axis, series) if series else None


_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")


def axis_figure_svg(axis: str, series: dict[str, list[tuple[float, float]]], width: int = 560,
                    height: int = 320) -> str:
    """An SVG line plot of the mean CD (mm) against ``axis``, one line per series (Fig. 10)."""
    xs = [x for pts in series.values() for x, _ in pts]
    ys = [y for pts in series.values() for _, y in pts]
    x0, x1 = min(xs), max(xs)
    y0, y1 = 0.0, max(ys) * 1.1 or 1.0
    left, right, top, bottom = 60, 170, 20, 45
    sx = lambda x: left + (x - x0) / ((x1 - x0) or 1.0) * (width - left - right)  # noqa: E731
    sy = lambda y: height - bottom - (y - y0) / (y1 - y0) * (height - top - bottom)  # noqa: E731
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" font-size="12">',
           f'<line x1="{left}" y1="{sy(y0)}" x2="{width - right}" y2="{sy(y0)}" stroke="black"/>',
           f'<line x1="{left}" y1="{sy(y0)}" x2="{left}" y2="{top}" stroke="black"/>']
    for x in sorted(set(xs)):
        out.append(f'<text x="{sx(x):.1f}" y="{height - bottom + 16}" text-anchor="middle">{x:g}</text>')
    for k in range(5):
        y = y0 + (y1 - y0) * k / 4
        out.append(f'<text x="{left - 6}" y="{sy(y) + 4:.1f}" text-anchor="end">{y:.2f}</text>')
    out.append(f'<text x="{(left + width - right) / 2}" y="{height - 8}" text-anchor="middle">'
               f'{html.escape(axis)}</text>')
    out.append(f'<text x="14" y="{(top + height - bottom) / 2}" text-anchor="middle" '
               f'transform="rotate(-90 14 {(top + height - bottom) / 2})">CD (mm)</text>')
    for i, (name, pts) in enumerate(series.items()):
        colour = _COLOURS[i % len(_COLOURS)]
        path = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in pts)
        out.append(f'<polyline points="{path}" fill="none" stroke="{colour}" stroke-width="2"/>')
        out += [f'<circle cx="{sx(x):.1f}" cy="{sy(y):.1f}" r="3" fill="{colour}"/>' for x, y in pts]
        out.append(f'<text x="{width - right + 10}" y="{top + 14 * (i + 1)}" fill="{colour}">'
                   f'{html.escape(name)}</text>')
    return "\n".join(out + ["</svg>"])


def method_grids(out: Path, limit: int = 24, tile_height: int = 240) -> list[tuple[str, bytes]]:
    """Per unit (at most ``limit``): a PNG of its cells' meshes, one column per row label, coloured
    by their distance to the unit's ground truth (front and top views, one scale), with each
    cell's CD under its name. Units whose ground truth is not recorded or no longer exists are
    left out."""
    from ..evaluation.render import render_grid_image
    from ..evaluation.sampling import sample_surface
    from ..io import load_mesh
    from ..pictures import png_bytes

    rows = finished_rows(out)
    by_unit: dict[str, list[tuple[str, dict]]] = {}
    for r, name in zip(rows, labels(rows)):
        by_unit.setdefault(r["unit"], []).append((name, r))
    pictures = []
    for unit in sorted(by_unit, key=_natural)[:limit]:
        cells = sorted(by_unit[unit], key=lambda c: _natural(c[0]))
        gt = next((Path(r["gt"]) for _, r in cells if r.get("gt")), None)
        if gt is None or not gt.exists() or not any(r["status"] == "ok" for _, r in cells):
            continue
        truth = load_mesh(gt)
        meshes, means = {}, {}
        for name, r in cells:
            mesh = out / "cells" / r["cell"] / "mesh.ply"
            meshes[name] = load_mesh(mesh) if r["status"] == "ok" and mesh.exists() else None
            means[name] = r.get("cd_mm")
        image = render_grid_image(meshes, sample_surface(truth, 100_000, seed=0), views=("front", "top"),
                                  tile_height=tile_height, means_mm=means)
        pictures.append((unit, png_bytes(image)))
    return pictures


def html_report(out: Path, baseline: str | None = None, decimals: int = 2, pictures: bool = True) -> str:
    """The whole report as one self-contained HTML page (tables, the swept-setting plot, the
    method grids as embedded PNGs): it opens offline and can be mailed as one file."""
    esc = html.escape
    parts = [f"<h1>ultraboneudf bench report</h1>\n<p>{esc(str(out.resolve()))}</p>"]
    parts += [format_table(t, "html", first_header=h) for t, h in _tables(out, baseline, decimals)]
    axis = swept_axis(finished_rows(out))
    if axis is not None:
        parts.append(f"<h2>CD against {esc(axis[0])}</h2>\n" + axis_figure_svg(*axis))
    if pictures:
        for unit, png in method_grids(out):
            data = base64.b64encode(png).decode("ascii")
            parts.append(f"<h2>{esc(unit)}: distance to the truth</h2>\n"
                         f'<img alt="{esc(unit)}" src="data:image/png;base64,{data}">')
    style = ("body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px}td{text-align:right}th{text-align:left}"
             "caption{font-weight:bold;text-align:left}img{max-width:100%}")
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>ultraboneudf bench report</title>"
            f"<style>{style}</style></head><body>\n" + "\n".join(parts) + "\n</body></html>\n")


def cost_table(out: Path, order: list[str] | None = None) -> Table:
    """Table 4 of the paper (experiment E2): per row label, the trainable parameters and the mean
    seconds of training and of the whole reconstruction over its finished cells (failures included:
    they cost time too)."""
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
