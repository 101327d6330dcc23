"""A self-contained interactive HTML viewer of a reconstruction coloured by distance (mm).

One HTML file, no network: the geometry is embedded as base64 (float32 positions relative to the
centre, uint32 triangle indices, float32 per-vertex distances) and drawn by a small WebGL2 program
written for this project (no third-party JavaScript). The colouring is the one of the PNG renders
(:mod:`.render`): distance to the ground truth clamped to ``[0, vmax]``, same colour ramp, the mean
written under the colour bar; a slider changes ``vmax``.

Controls: left drag orbits, wheel zooms, right drag (or shift + drag) pans, double click resets.
Check boxes show or hide the reconstruction, the ground truth (a translucent grey ghost) and the
input points. Faces are lit from both sides, since UDF meshes are not consistently oriented.

When the first frame has been drawn the element ``#status`` reads ``ready webgl2 …`` (or
``error: …``); tests read it with a headless browser.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
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
            .replace("__SCRIPT__", _SCRIPT))


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
__SCRIPT__
</script>
</body>
</html>
"""

_SCRIPT = r"""
"use strict";
(function () {
  const status = document.getElementById("status");
  function fail(msg) { status.textContent = "error: " + msg; status.style.color = "#b00"; }
  let meta, bytes;
  try {
    meta = JSON.parse(document.getElementById("meta").textContent);
    const b64 = document.getElementById("data").textContent.trim();
    const bin = atob(b64);
    bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  } catch (e) { fail("cannot decode the embedded data: " + e); return; }
  const buf = bytes.buffer;
  const f32 = (off, n) => new Float32Array(buf, off, n);
  const u32 = (off, n) => new Uint32Array(buf, off, n);

  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl2", { antialias: true, preserveDrawingBuffer: true });
  if (!gl) { fail("this browser has no WebGL2"); return; }

  // ---- shaders -------------------------------------------------------------------------------
  const VS = `#version 300 es
  in vec3 aPos; in float aVal;
  uniform mat4 uView; uniform mat4 uProj; uniform float uPointSize;
  out vec3 vEye; out float vVal;
  void main() {
    vec4 e = uView * vec4(aPos, 1.0);
    vEye = e.xyz; vVal = aVal;
    gl_Position = uProj * e;
    gl_PointSize = uPointSize;
  }`;
  const FS = `#version 300 es
  precision highp float;
  in vec3 vEye; in float vVal;
  uniform int uMode;            // 0: distance colours, 1: flat colour, 2: round points
  uniform vec3 uColor; uniform float uAlpha; uniform float uVmax;
  uniform vec3 uStops[5]; uniform float uPos[5];
  out vec4 outColor;
  vec3 ramp(float t) {
    t = clamp(t, 0.0, 1.0);
    for (int i = 0; i < 4; i++) {
      if (t <= uPos[i + 1]) return mix(uStops[i], uStops[i + 1], (t - uPos[i]) / (uPos[i + 1] - uPos[i]));
    }
    return uStops[4];
  }
  void main() {
    if (uMode == 2) {
      vec2 c = gl_PointCoord - vec2(0.5);
      if (dot(c, c) > 0.25) discard;
      outColor = vec4(uColor, 1.0);
      return;
    }
    vec3 n = normalize(cross(dFdx(vEye), dFdy(vEye)));
    vec3 toEye = normalize(-vEye);
    vec3 key = normalize(vec3(-0.45, 0.55, 1.0));
    vec3 halfv = normalize(key + toEye);
    float light = 0.22 + 0.48 * abs(dot(n, toEye)) + 0.30 * abs(dot(n, key));   // two-sided
    float spec = 0.12 * pow(abs(dot(n, halfv)), 40.0);
    vec3 base = (uMode == 0) ? ramp(vVal / uVmax) : uColor;
    outColor = vec4(min(base * light + vec3(spec), vec3(1.0)), uAlpha);
  }`;
  function compile(type, src) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }
  let prog;
  try {
    prog = gl.createProgram();
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, FS));
    gl.bindAttribLocation(prog, 0, "aPos");
    gl.bindAttribLocation(prog, 1, "aVal");
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  } catch (e) { fail("shader: " + e.message); return; }
  gl.useProgram(prog);
  const U = {};
  for (const name of ["uView", "uProj", "uPointSize", "uMode", "uColor", "uAlpha", "uVmax", "uStops", "uPos"]) {
    U[name] = gl.getUniformLocation(prog, name);
  }
  gl.uniform3fv(U.uStops, meta.stops.flatMap(s => s[1]));
  gl.uniform1fv(U.uPos, meta.stops.map(s => s[0]));

  // ---- geometry ------------------------------------------------------------------------------
  function layer(L, isMesh) {
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const n = isMesh ? L.vertices : L.count;
    const pb = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, pb);
    gl.bufferData(gl.ARRAY_BUFFER, f32(L.positions, 3 * n), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    if (L.values !== undefined) {
      const vb = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, vb);
      gl.bufferData(gl.ARRAY_BUFFER, f32(L.values, n), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(1);
      gl.vertexAttribPointer(1, 1, gl.FLOAT, false, 0, 0);
    } else {
      gl.disableVertexAttribArray(1);
      gl.vertexAttrib1f(1, 0.0);
    }
    let count = n;
    if (isMesh) {
      const ib = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, u32(L.indices, 3 * L.triangles), gl.STATIC_DRAW);
      count = 3 * L.triangles;
    }
    gl.bindVertexArray(null);
    return { vao: vao, count: count, colored: L.values !== undefined };
  }
  const recon = layer(meta.recon, true);
  const gt = meta.gt ? layer(meta.gt, true) : null;
  const pts = meta.points ? layer(meta.points, false) : null;
  if (!gt) document.getElementById("row-gt").style.display = "none";
  if (!pts) document.getElementById("row-points").style.display = "none";
  if (!recon.colored) document.getElementById("legend").style.display = "none";

  // ---- camera --------------------------------------------------------------------------------
  const up = [0, 0, 0]; up[meta.up] = 1;
  const fwd = [0, 0, 0]; fwd[(meta.up + 1) % 3] = 1;
  const side = [up[1] * fwd[2] - up[2] * fwd[1], up[2] * fwd[0] - up[0] * fwd[2], up[0] * fwd[1] - up[1] * fwd[0]];
  // The first view (and a double click) frames the bounding sphere in the narrower of the two
  // fields of view (30° vertical), with a 10% margin.
  function fitDistance() {
    const aspect = Math.max(1e-3, (canvas.clientWidth || 1) / (canvas.clientHeight || 1));
    const half = Math.atan(Math.tan(15 * Math.PI / 180) * Math.min(1, aspect));
    return 1.1 * meta.radius / Math.sin(half);
  }
  function homeView() { return { az: 0.6, el: 0.25, dist: fitDistance(), target: [0, 0, 0] }; }
  let cam = homeView();
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const norm = a => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
  function eyeDir() {
    const ce = Math.cos(cam.el), se = Math.sin(cam.el), ca = Math.cos(cam.az), sa = Math.sin(cam.az);
    return [0, 1, 2].map(i => ce * (ca * fwd[i] + sa * side[i]) + se * up[i]);
  }
  function viewMatrix() {
    const w = eyeDir();
    const eye = [0, 1, 2].map(i => cam.target[i] + cam.dist * w[i]);
    let r = cross(up, w);
    if (Math.hypot(r[0], r[1], r[2]) < 1e-6) r = side;
    r = norm(r);
    const u = cross(w, r);
    return [r[0], u[0], w[0], 0, r[1], u[1], w[1], 0, r[2], u[2], w[2], 0,
            -dot(r, eye), -dot(u, eye), -dot(w, eye), 1];
  }
  function projMatrix(aspect) {
    const f = 1 / Math.tan(0.5 * 30 * Math.PI / 180);
    const near = Math.max(cam.dist - 2.5 * meta.radius, cam.dist * 0.01), far = cam.dist + 2.5 * meta.radius;
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, 2 * far * near / (near - far), 0];
  }

  // ---- drawing -------------------------------------------------------------------------------
  const ui = {
    recon: document.getElementById("show-recon"), gt: document.getElementById("show-gt"),
    points: document.getElementById("show-points"), vmax: document.getElementById("vmax"),
  };
  ui.vmax.value = meta.vmax;
  const stopsCss = meta.stops.map(s => "rgb(" + s[1].map(c => Math.round(255 * c)).join(",") + ") " + (100 * s[0]) + "%");
  document.getElementById("bar").style.background = "linear-gradient(to right, " + stopsCss.join(", ") + ")";
  if (meta.mean !== null) document.getElementById("mean").textContent = "mean " + meta.mean.toFixed(2) + " mm";
  function updateLegend() { document.getElementById("vmax-label").textContent = Number(ui.vmax.value) + "+ mm"; }
  updateLegend();

  function resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  }
  function draw() {
    resize();
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(1, 1, 1, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);   // double-sided
    gl.uniformMatrix4fv(U.uView, false, viewMatrix());
    gl.uniformMatrix4fv(U.uProj, false, projMatrix(canvas.width / canvas.height));
    gl.uniform1f(U.uVmax, Number(ui.vmax.value));
    gl.uniform1f(U.uPointSize, Math.max(2.0, 2.0 * (window.devicePixelRatio || 1)));
    gl.disable(gl.BLEND); gl.depthMask(true);
    if (ui.recon.checked) {
      gl.uniform1i(U.uMode, recon.colored ? 0 : 1);
      gl.uniform3f(U.uColor, 0.78, 0.78, 0.77); gl.uniform1f(U.uAlpha, 1.0);
      gl.bindVertexArray(recon.vao); gl.drawElements(gl.TRIANGLES, recon.count, gl.UNSIGNED_INT, 0);
    }
    if (pts && ui.points.checked) {
      gl.uniform1i(U.uMode, 2); gl.uniform3f(U.uColor, 0.1, 0.1, 0.1); gl.uniform1f(U.uAlpha, 1.0);
      gl.bindVertexArray(pts.vao); gl.drawArrays(gl.POINTS, 0, pts.count);
    }
    if (gt && ui.gt.checked) {   // translucent ghost, drawn last without writing depth
      gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false);
      gl.uniform1i(U.uMode, 1); gl.uniform3f(U.uColor, 0.6, 0.6, 0.62); gl.uniform1f(U.uAlpha, 0.35);
      gl.bindVertexArray(gt.vao); gl.drawElements(gl.TRIANGLES, gt.count, gl.UNSIGNED_INT, 0);
      gl.depthMask(true); gl.disable(gl.BLEND);
    }
    gl.bindVertexArray(null);
  }
  let pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; draw(); }); } }

  // ---- interaction ---------------------------------------------------------------------------
  let drag = null;
  canvas.addEventListener("contextmenu", e => e.preventDefault());
  canvas.addEventListener("pointerdown", e => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId); canvas.style.cursor = "grabbing";
  });
  canvas.addEventListener("pointerup", e => { drag = null; canvas.style.cursor = "grab"; });
  canvas.addEventListener("pointermove", e => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const v = viewMatrix(), k = 2 * cam.dist * Math.tan(15 * Math.PI / 180) / canvas.clientHeight;
      const r = [v[0], v[4], v[8]], u = [v[1], v[5], v[9]];
      cam.target = [0, 1, 2].map(i => cam.target[i] - k * (dx * r[i] - dy * u[i]));
    } else {
      cam.az -= dx * 0.008;
      cam.el = Math.max(-1.55, Math.min(1.55, cam.el + dy * 0.008));
    }
    redraw();
  });
  canvas.addEventListener("wheel", e => {
    e.preventDefault();
    cam.dist = Math.max(0.05 * meta.radius, Math.min(20 * meta.radius, cam.dist * Math.exp(e.deltaY * 0.001)));
    redraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { cam = homeView(); redraw(); });
  for (const el of [ui.recon, ui.gt, ui.points]) el.addEventListener("change", redraw);
  ui.vmax.addEventListener("input", () => { updateLegend(); redraw(); });
  window.addEventListener("resize", redraw);

  // ---- first frame, drawn synchronously so that headless checks see it -------------------------
  try {
    draw();
    const px = new Uint8Array(4 * 64 * 64);
    gl.readPixels(Math.floor(canvas.width / 2) - 32, Math.floor(canvas.height / 2) - 32, 64, 64, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let drawn = 0;
    for (let i = 0; i < px.length; i += 4) if (px[i] < 250 || px[i + 1] < 250 || px[i + 2] < 250) drawn++;
    const err = gl.getError();
    if (err !== gl.NO_ERROR) { fail("WebGL error " + err); return; }
    status.textContent = "ready webgl2 triangles=" + meta.recon.triangles + " centre_pixels_drawn=" + drawn;
    status.dataset.ready = "1";
  } catch (e) { fail(e.message); }
})();
"""
