"""A self-contained interactive HTML viewer of a reconstruction coloured by distance (mm).

One HTML file, no network: the geometry is embedded as base64 (float32 positions relative to the
centre, uint32 triangle indices, float32 per-vertex distances) and drawn by a small WebGL2 program
written for this project (no third-party JavaScript), kept beside this module as ``viewer.js``
(package data). The colouring is the one of the PNG renders (:mod:`.render`): distance to the
ground truth clamped to ``[0, vmax]``, same colour ramp, the mean written under the colour bar; a
slider changes ``vmax``.

Controls: left drag orbits, wheel zooms, right drag (or shift + drag) pans, double click resets.
Check boxes show or hide the reconstruction, the ground truth (a translucent grey ghost) and the
input points. Faces are lit from both sides, since UDF meshes are not consistently oriented.

When the first frame has been drawn the element ``#status`` reads ``ready webgl2 …`` (or
``error: …``); tests read it with a headless browser.
"""

from __future__ import annotations

import base64
import functools
import html
import json
import math
import os
from importlib import resources
from typing import Optional

import numpy as np

from ..io import atomic_write_bytes
from .render import COLOR_STOPS, DEFAULT_VMAX_MM, area_weighted_mean, vertex_distances
from .sampling import MeshLike, mesh_arrays

DEFAULT_MAX_POINTS = 200_000


class _Blob:
    """Concatenated little-endian arrays, each aligned to 4 bytes, with their offsets."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0

    def add(self, array: np.ndarray) -> int:
        data = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
        offset = self.size
        self.parts.append(data)
        self.size += len(data)
        return offset

    def b64(self) -> str:
        return base64.b64encode(b"".join(self.parts)).decode("ascii")


def _mesh_layer(blob: _Blob, mesh: MeshLike, centre: np.ndarray, values: Optional[np.ndarray],
                source: str) -> dict:
    v, f = mesh_arrays(mesh, source)
    ok = np.isfinite(v).all(axis=1)
    if not ok.all():  # drop faces touching non-finite vertices (they cannot be drawn)
        f = f[ok[f].all(axis=1)]
        v = np.where(ok[:, None], v, 0.0)
    layer = {
        "positions": blob.add((v - centre).astype(np.float32)),
        "vertices": int(len(v)),
        "indices": blob.add(f.astype(np.uint32)),
        "triangles": int(len(f)),
    }
    if values is not None:
        layer["values"] = blob.add(np.nan_to_num(np.asarray(values, dtype=np.float64), nan=1e9).astype(np.float32))
    return layer


def viewer_html(mesh: MeshLike, reference: Optional[np.ndarray] = None, ground_truth: Optional[MeshLike] = None,
                points: Optional[np.ndarray] = None, title: str = "reconstruction",
                vmax: float = DEFAULT_VMAX_MM, max_points: int = DEFAULT_MAX_POINTS, seed: int = 0,
                mean_mm: Optional[float] = None, up_axis: Optional[int] = None,
                label: str = "reconstruction") -> str:
    """The viewer page as a string.

    ``mesh``: the reconstruction (mm). ``reference``: ground-truth points to colour by (e.g.
    :func:`~.render.reference_points`); ``None`` draws it grey. ``ground_truth``: mesh shown as a
    toggleable ghost. ``points``: input cloud (mm), randomly thinned to ``max_points`` (seeded).
    ``mean_mm`` overrides the mean written under the colour bar (NaN: none written). ``label``
    names ``mesh`` beside its check box.
    """
    v, f = mesh_arrays(mesh, "reconstruction")
    finite = v[np.isfinite(v).all(axis=1)]
    if len(finite) == 0:
        raise ValueError("viewer: the reconstruction has no finite vertices")
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = float(np.linalg.norm(hi - lo) / 2.0) or 1.0
    if up_axis is None:
        up_axis = int(np.argmax(hi - lo))
    values = None
    if reference is not None:
        values = vertex_distances(v, reference)
        if mean_mm is None:
            mean_mm = area_weighted_mean(v, f, values)
    blob = _Blob()
    meta: dict = {
        "title": title, "vmax": float(vmax), "up": up_axis, "radius": radius,
        "stops": [[p, [c / 255.0 for c in rgb]] for p, rgb in COLOR_STOPS],
        "mean": None if mean_mm is None or math.isnan(mean_mm) else float(mean_mm),
        "recon": _mesh_layer(blob, (v, f), centre, values, "reconstruction"),
    }
    if ground_truth is not None:
        meta["gt"] = _mesh_layer(blob, ground_truth, centre, None, "ground truth")
    if points is not None:
        pts = np.asarray(points, dtype=np.float64)[:, :3]
        pts = pts[np.isfinite(pts).all(axis=1)]
        if len(pts) > max_points:
            pts = pts[np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))]
        meta["points"] = {"positions": blob.add((pts - centre).astype(np.float32)), "count": int(len(pts))}
    meta_json = json.dumps(meta).replace("</", "<\\/")
    return (_PAGE.replace("__TITLE__", html.escape(title)).replace("__LABEL__", html.escape(label))
            .replace("__META__", meta_json)
            .replace("__DATA__", blob.b64())
            .replace("__SCRIPT__", _script()))


@functools.cache
def _script() -> str:
    """The viewer's WebGL2 program: ``viewer.js``, package data beside this module."""
    return resources.files(__package__).joinpath("viewer.js").read_text(encoding="utf-8")


def write_viewer(path: str | os.PathLike, mesh: MeshLike, **kwargs) -> None:
    """Write :func:`viewer_html` to ``path`` atomically (UTF-8)."""
    atomic_write_bytes(path, viewer_html(mesh, **kwargs).encode("utf-8"))


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>__TITLE__ — ultraboneudf viewer</title>
<style>
  html, body { margin: 0; height: 100%; overflow: hidden; background: #fff; font: 14px system-ui, sans-serif; }
  #view { position: absolute; inset: 0; width: 100%; height: 100%; display: block; cursor: grab; }
  #panel { position: absolute; top: 10px; left: 10px; background: rgba(255,255,255,0.88);
           border: 1px solid #ccc; border-radius: 6px; padding: 8px 10px; max-width: 260px; }
  #panel h1 { font-size: 15px; margin: 0 0 6px 0; }
  #panel label { display: block; margin: 2px 0; }
  #bar { height: 14px; border: 1px solid #555; margin-top: 8px; }
  #ticks { display: flex; justify-content: space-between; font-size: 12px; }
  #mean { margin-top: 4px; font-weight: 600; }
  #help { margin-top: 6px; font-size: 11px; color: #555; }
  #status { position: absolute; bottom: 4px; right: 8px; font-size: 11px; color: #888; }
</style>
</head>
<body>
<canvas id="view"></canvas>
<div id="panel">
  <h1 id="title">__TITLE__</h1>
  <label><input type="checkbox" id="show-recon" checked> __LABEL__</label>
  <label id="row-gt"><input type="checkbox" id="show-gt"> ground truth</label>
  <label id="row-points"><input type="checkbox" id="show-points"> input points</label>
  <div id="legend">
    <div id="bar"></div>
    <div id="ticks"><span>0</span><span id="vmax-label"></span></div>
    <div id="mean"></div>
    <label>colour range <input type="range" id="vmax" min="0.5" max="20" step="0.5"></label>
  </div>
  <div id="help">drag: orbit · wheel: zoom · right drag / shift drag: pan · double click: reset</div>
</div>
<div id="status">loading</div>
<script type="application/json" id="meta">__META__</script>
<script type="application/octet-stream" id="data">__DATA__</script>
<script>
__SCRIPT__</script>
</body>
</html>
"""
