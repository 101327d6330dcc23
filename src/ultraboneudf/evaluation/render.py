"""Distance-coloured pictures of reconstructions (headless PNG), as the paper's Figs. 7–9.

Colour = distance (mm) from the reconstruction to the ground truth, clamped to ``[0, vmax]``
(default 0–5 mm), with a colour bar and the mean distance written under it. Several views of one
mesh side by side (:func:`render_distance_png`), or a grid of methods × views with one colour bar
(:func:`render_grid_png`).

Rendering is a small NumPy rasteriser, not matplotlib: matplotlib's 3-D axes sort whole polygons
(painter's order), which is wrong for interpenetrating surfaces and slow for a large mesh, while a
vectorised z-buffer decides visibility per pixel. Each face is expanded into the pixel centres of
its bounding box, barycentric coordinates decide coverage, and the nearest depth wins. Shading is
flat per face and two-sided (``|n·l|``), because UDF meshes are not consistently oriented. Images
are drawn at 2× and box-filtered down (anti-aliasing). Pillow writes the PNG and draws the text
(:mod:`~ultraboneudf.pictures`).

Distances are per vertex: each vertex's distance to the nearest of ``colour_samples`` area-uniform
ground-truth samples (after the pseudo-GT filter when raw points are given), interpolated across
faces. The mean under the bar is the area-weighted mean of these vertex distances, an estimate of
mean ``d_RG`` (docs/ALGORITHMS.md §6.2).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..errors import InputError
from ..geometry.neighbors import kd_tree
from ..geometry.vectors import unit_rows
from ..io import atomic_write_bytes
from ..pictures import pil, png_bytes, ramp, text_font
from .sampling import MeshLike, face_areas, mesh_arrays

# colour ramp (position in [0, 1], RGB 0–255): blue → cyan → green → yellow → red
COLOR_STOPS: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.00, (38, 64, 198)),
    (0.25, (36, 168, 226)),
    (0.50, (64, 196, 96)),
    (0.75, (246, 206, 46)),
    (1.00, (212, 42, 38)),
)
GT_COLOR = (200, 200, 196)
"""Colour of meshes drawn without distances (ground truth, or no ground truth given)."""
BACKGROUND = (255, 255, 255)
DEFAULT_VMAX_MM = 5.0
DEFAULT_COLOUR_SAMPLES = 1_000_000

VIEWS: dict[str, tuple[float, float]] = {
    "front": (0.0, 0.0), "right": (90.0, 0.0), "back": (180.0, 0.0), "left": (270.0, 0.0),
    "top": (0.0, 90.0), "bottom": (0.0, -90.0),
}
"""Named views as (azimuth, elevation) in degrees about the up axis."""
DEFAULT_VIEWS = ("front", "right", "back")


def colormap(values: np.ndarray, vmax: float = DEFAULT_VMAX_MM) -> np.ndarray:
    """RGB ``(..., 3)`` float in [0, 255] for distances ``values`` (mm) clamped to ``[0, vmax]``."""
    return ramp(np.asarray(values, dtype=np.float64) / float(vmax), COLOR_STOPS)


# --------------------------------------------------------------------------------------------
# distances


def vertex_distances(vertices: np.ndarray, reference_points: np.ndarray, workers: int = -1) -> np.ndarray:
    """Distance (mm) from each vertex ``(V, 3)`` to the nearest reference point; ``(V,)`` float64.

    Non-finite vertices get NaN.
    """
    v = np.asarray(vertices, dtype=np.float64)
    out = np.full(len(v), np.nan)
    ok = np.isfinite(v).all(axis=1)
    if ok.any():
        out[ok] = kd_tree(np.asarray(reference_points, dtype=np.float64)).query(v[ok], workers=workers)[0]
    return out


def area_weighted_mean(vertices: np.ndarray, faces: np.ndarray, values: np.ndarray) -> float:
    """Mean of per-vertex ``values`` over the surface (each face contributes area/3 per corner)."""
    area = face_areas(vertices, faces)
    w = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))
    ok = np.isfinite(values) & (w > 0)
    return float(np.sum(w[ok] * values[ok]) / np.sum(w[ok])) if ok.any() else math.nan


def reference_points(gt: MeshLike, raw_points: Optional[np.ndarray] = None,
                     pseudo_gt_mm: Optional[float] = None, samples: int = DEFAULT_COLOUR_SAMPLES,
                     seed: int = 0) -> np.ndarray:
    """Ground-truth samples to colour by: area-uniform on ``gt``, pseudo-GT filtered when
    ``raw_points`` is given (τ defaults to 2 mm), as in :func:`~.metrics.prepare_ground_truth`."""
    from .metrics import prepare_ground_truth

    return prepare_ground_truth(gt, raw_points, pseudo_gt_mm, samples, seed).points


# --------------------------------------------------------------------------------------------
# camera and rasteriser


@dataclass(frozen=True)
class Camera:
    """Orthographic camera: screen axes ``right``, ``up``; ``toward`` points from the scene to the eye."""

    right: np.ndarray
    up: np.ndarray
    toward: np.ndarray


def camera(view: str | tuple[float, float], up_axis: int = 2) -> Camera:
    """The camera of a named view (see :data:`VIEWS`) or an (azimuth, elevation) pair in degrees."""
    if isinstance(view, str):
        if view not in VIEWS:
            raise InputError(f"unknown view {view!r}; use one of {', '.join(VIEWS)} or 'AZ:EL' degrees")
        az, el = VIEWS[view]
    else:
        az, el = float(view[0]), float(view[1])
    u = np.eye(3)[up_axis]
    f0 = np.eye(3)[(up_axis + 1) % 3]
    s0 = np.cross(u, f0)
    a, e = math.radians(az), math.radians(el)
    w = math.cos(e) * (math.cos(a) * f0 + math.sin(a) * s0) + math.sin(e) * u
    r = np.cross(u, w)
    if np.linalg.norm(r) < 1e-6:  # looking straight down or up: keep the azimuth's right vector
        r = -math.sin(a) * f0 + math.cos(a) * s0
    r /= np.linalg.norm(r)
    v = np.cross(w, r)
    return Camera(right=r, up=v / np.linalg.norm(v), toward=w / np.linalg.norm(w))


def parse_view(text: str) -> str | tuple[float, float]:
    """``"front"`` or ``"30:15"`` (azimuth:elevation in degrees)."""
    text = text.strip()
    if ":" in text:
        try:
            az, el = (float(x) for x in text.split(":"))
        except ValueError:
            raise InputError(f"view {text!r}: expected AZ:EL in degrees, e.g. 30:15") from None
        return az, el
    if text not in VIEWS:
        raise InputError(f"unknown view {text!r}; use one of {', '.join(VIEWS)} or AZ:EL degrees")
    return text


def rasterize(xy: np.ndarray, depth: np.ndarray, faces: np.ndarray, width: int, height: int,
              max_candidates: int = 1 << 22) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Z-buffer rasterisation of triangles given in pixel coordinates.

    ``xy`` ``(V, 2)``: column, row (row grows downward); ``depth`` ``(V,)``: smaller is nearer.
    Returns ``face (H, W)`` int64 (−1 = background) and barycentric weights ``b1, b2`` ``(H, W)`` of
    the face's second and third corner. Faces whose corners are not all finite are skipped.
    """
    n_pix = width * height
    zbuf = np.full(n_pix, np.inf)
    face_buf = np.full(n_pix, -1, dtype=np.int64)
    b1_buf = np.zeros(n_pix)
    b2_buf = np.zeros(n_pix)
    if len(faces) == 0:
        return face_buf.reshape(height, width), b1_buf.reshape(height, width), b2_buf.reshape(height, width)
    p = xy[faces]  # (F, 3, 2)
    z = depth[faces]
    ok = np.isfinite(p).all(axis=(1, 2)) & np.isfinite(z).all(axis=1)
    x0 = np.ceil(p[..., 0].min(axis=1) - 0.5)
    x1 = np.floor(p[..., 0].max(axis=1) - 0.5)
    y0 = np.ceil(p[..., 1].min(axis=1) - 0.5)
    y1 = np.floor(p[..., 1].max(axis=1) - 0.5)
    with np.errstate(invalid="ignore"):
        x0 = np.clip(x0, 0, width - 1)
        x1 = np.clip(x1, 0, width - 1)
        y0 = np.clip(y0, 0, height - 1)
        y1 = np.clip(y1, 0, height - 1)
        ok &= (x1 >= x0) & (y1 >= y0)
    px0, py0 = p[:, 0, 0], p[:, 0, 1]
    px1, py1 = p[:, 1, 0], p[:, 1, 1]
    px2, py2 = p[:, 2, 0], p[:, 2, 1]
    den = (py1 - py2) * (px0 - px2) + (px2 - px1) * (py0 - py2)
    ok &= np.abs(den) > 1e-12
    ids = np.flatnonzero(ok)
    if len(ids) == 0:
        return face_buf.reshape(height, width), b1_buf.reshape(height, width), b2_buf.reshape(height, width)
    bw = (x1[ids] - x0[ids] + 1).astype(np.int64)
    bh = (y1[ids] - y0[ids] + 1).astype(np.int64)
    cost = bw * bh
    bounds = np.searchsorted(np.cumsum(cost), np.arange(max_candidates, int(cost.sum()) + max_candidates,
                                                        max_candidates), side="right")
    start = 0
    cand_pid, cand_fid, cand_b1, cand_b2, cand_z = [], [], [], [], []
    for stop in np.unique(np.r_[bounds, len(ids)]):
        stop = max(int(stop), start + 1)
        if start >= len(ids):
            break
        sel = ids[start:stop]
        c = cost[start:stop]
        w_ = bw[start:stop]
        rep = np.repeat(np.arange(len(sel)), c)
        local = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        f = sel[rep]
        cx = x0[f] + local % w_[rep] + 0.5
        cy = y0[f] + local // w_[rep] + 0.5
        d = den[f]
        l0 = ((py1[f] - py2[f]) * (cx - px2[f]) + (px2[f] - px1[f]) * (cy - py2[f])) / d
        l1 = ((py2[f] - py0[f]) * (cx - px2[f]) + (px0[f] - px2[f]) * (cy - py2[f])) / d
        l2 = 1.0 - l0 - l1
        inside = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
        f, l1, l2, l0, cx, cy = f[inside], l1[inside], l2[inside], l0[inside], cx[inside], cy[inside]
        cand_pid.append((cy - 0.5).astype(np.int64) * width + (cx - 0.5).astype(np.int64))
        cand_fid.append(f)
        cand_b1.append(l1)
        cand_b2.append(l2)
        cand_z.append(l0 * z[f, 0] + l1 * z[f, 1] + l2 * z[f, 2])
        start = stop
    pid = np.concatenate(cand_pid)
    zc = np.concatenate(cand_z)
    np.minimum.at(zbuf, pid, zc)
    win = zc <= zbuf[pid]
    face_buf[pid[win]] = np.concatenate(cand_fid)[win]
    b1_buf[pid[win]] = np.concatenate(cand_b1)[win]
    b2_buf[pid[win]] = np.concatenate(cand_b2)[win]
    return face_buf.reshape(height, width), b1_buf.reshape(height, width), b2_buf.reshape(height, width)


@dataclass(frozen=True)
class Framing:
    """World → pixel map shared by all tiles of a figure: centre (3,), pixels per mm, tile size."""

    centre: np.ndarray
    scale: float
    width: int
    height: int


def frame(points: np.ndarray, cameras: Sequence[Camera], tile_height: int = 480,
          margin: float = 0.06) -> Framing:
    """Fit the bounding box of ``points`` into one tile size for every camera (same scale)."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise InputError("nothing to render: no finite vertices")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2.0
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - centre
    ext_w = max(float(np.ptp(corners @ c.right)) for c in cameras) or 1.0
    ext_h = max(float(np.ptp(corners @ c.up)) for c in cameras) or 1.0
    aspect = min(3.0, max(0.35, ext_w / ext_h))
    width = int(round(tile_height * aspect))
    scale = (1.0 - 2 * margin) * min(width / ext_w, tile_height / ext_h)
    return Framing(centre=centre, scale=scale, width=width, height=int(tile_height))


def render_view(vertices: np.ndarray, faces: np.ndarray, cam: Camera, framing: Framing,
                values: Optional[np.ndarray] = None, vmax: float = DEFAULT_VMAX_MM,
                color: tuple[int, int, int] = GT_COLOR, supersample: int = 2) -> np.ndarray:
    """One view as an ``(H, W, 3)`` uint8 image on a white background.

    ``values`` ``(V,)``: per-vertex distances (mm) coloured by :func:`colormap`; ``None``: plain
    ``color``. Two-sided flat shading with a head light and a key light from the upper left.
    """
    ss = max(1, int(supersample))
    W, H = framing.width * ss, framing.height * ss
    rel = np.asarray(vertices, dtype=np.float64) - framing.centre
    s = framing.scale * ss
    xy = np.stack([W / 2 + (rel @ cam.right) * s, H / 2 - (rel @ cam.up) * s], axis=1)
    depth = -(rel @ cam.toward)
    fbuf, b1, b2 = rasterize(xy, depth, faces, W, H)
    img = np.empty((H, W, 3), dtype=np.float64)
    img[:] = BACKGROUND
    hit = fbuf >= 0
    if hit.any():
        f = fbuf[hit]
        tri = faces[f]
        a = np.asarray(vertices, dtype=np.float64)
        n = unit_rows(np.cross(a[tri[:, 1]] - a[tri[:, 0]], a[tri[:, 2]] - a[tri[:, 0]]))
        head = cam.toward
        key = 0.45 * cam.right * -1 + 0.55 * cam.up + cam.toward
        key /= np.linalg.norm(key)
        half = (key + cam.toward) / np.linalg.norm(key + cam.toward)
        diffuse = 0.22 + 0.48 * np.abs(n @ head) + 0.30 * np.abs(n @ key)
        spec = 0.12 * np.abs(n @ half) ** 40
        if values is None:
            base = np.broadcast_to(np.asarray(color, dtype=np.float64), (len(f), 3))
        else:
            vals = np.asarray(values, dtype=np.float64)
            w1, w2 = b1[hit], b2[hit]
            interp = (1 - w1 - w2) * vals[tri[:, 0]] + w1 * vals[tri[:, 1]] + w2 * vals[tri[:, 2]]
            base = colormap(np.nan_to_num(interp, nan=vmax), vmax)
        img[hit] = np.clip(base * diffuse[:, None] + 255.0 * spec[:, None], 0, 255)
    if ss > 1:
        img = img.reshape(framing.height, ss, framing.width, ss, 3).mean(axis=(1, 3))
    return np.round(img).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# composition


def _colour_bar(height: int, vmax: float, mean_text: Optional[str], scale: float = 1.0):
    """A vertical colour bar panel (PIL image): ticks 0…vmax mm, the mean written under the bar."""
    Image, ImageDraw, _ = pil()
    width = int(120 * scale)
    panel = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(panel)
    font = text_font(int(15 * scale))
    bar_w = int(22 * scale)
    top, bottom = int(40 * scale), height - int(70 * scale)
    bottom = max(bottom, top + 20)
    x0 = int(14 * scale)
    t = np.linspace(1.0, 0.0, bottom - top)[:, None]
    grad = colormap(t * vmax, vmax).astype(np.uint8)
    panel.paste(Image.fromarray(np.repeat(grad, bar_w, axis=1)), (x0, top))
    draw.rectangle([x0 - 1, top - 1, x0 + bar_w, bottom], outline=(60, 60, 60))
    draw.text((x0 - 4, top - int(30 * scale)), "distance", fill=(30, 30, 30), font=font)
    step = 1.0 if vmax <= 8 else (2.0 if vmax <= 16 else 5.0)
    ticks = np.arange(0.0, vmax + 1e-9, step) if vmax >= 1 else np.linspace(0, vmax, 3)
    for v in ticks:
        y = int(round(bottom - (bottom - top) * v / vmax))
        draw.line([x0 + bar_w, y, x0 + bar_w + int(5 * scale), y], fill=(60, 60, 60))
        label = f"{v:g}" + (" mm" if v == ticks[-1] else "")
        if v == ticks[-1] and vmax == ticks[-1]:
            label = f"{v:g}+ mm"  # values above vmax are drawn in the top colour
        draw.text((x0 + bar_w + int(8 * scale), y - int(8 * scale)), label, fill=(30, 30, 30), font=font)
    if mean_text:
        draw.text((x0 - 4, bottom + int(14 * scale)), mean_text, fill=(0, 0, 0), font=font)
    return panel


@dataclass(frozen=True)
class Colored:
    """A mesh ready to draw: arrays, per-vertex distances (or ``None``) and its mean (mm)."""

    vertices: np.ndarray
    faces: np.ndarray
    values: Optional[np.ndarray]
    mean_mm: Optional[float]


def colour_mesh(mesh: MeshLike, reference: Optional[np.ndarray], source: str = "mesh") -> Colored:
    """Vertex distances of ``mesh`` to ``reference`` points (``None``: no colouring)."""
    v, f = mesh_arrays(mesh, source)
    if reference is None:
        return Colored(v, f, None, None)
    d = vertex_distances(v, reference)
    return Colored(v, f, d, area_weighted_mean(v, f, d))


def _mean_text(mean_mm: Optional[float]) -> Optional[str]:
    return None if mean_mm is None or math.isnan(mean_mm) else f"mean {mean_mm:.2f} mm"


def render_distance_image(mesh: MeshLike, reference: Optional[np.ndarray] = None,
                          views: Sequence[str | tuple[float, float]] = DEFAULT_VIEWS,
                          tile_height: int = 480, vmax: float = DEFAULT_VMAX_MM, up_axis: Optional[int] = None,
                          title: Optional[str] = None, mean_mm: Optional[float] = None):
    """A PIL image: ``mesh`` from several ``views`` side by side, coloured by distance to
    ``reference`` points (mm), with a colour bar and the mean under it. ``mean_mm`` overrides the
    written mean (e.g. pass the CD); ``reference=None`` draws a plain grey mesh without a bar."""
    Image, ImageDraw, _ = pil()
    col = colour_mesh(mesh, reference)
    if up_axis is None:
        finite = col.vertices[np.isfinite(col.vertices).all(axis=1)]
        up_axis = int(np.argmax(np.ptp(finite, axis=0))) if len(finite) else 2
    cams = [camera(v, up_axis) for v in views]
    framing = frame(col.vertices, cams, tile_height)
    tiles = [render_view(col.vertices, col.faces, c, framing, col.values, vmax) for c in cams]
    title_h = int(tile_height * 0.08) if title else 0
    width = framing.width * len(tiles)
    bar = _colour_bar(framing.height, vmax, _mean_text(col.mean_mm if mean_mm is None else mean_mm),
                      scale=max(0.75, tile_height / 480)) if col.values is not None else None
    canvas = Image.new("RGB", (width + (bar.width if bar else 0), framing.height + title_h), BACKGROUND)
    for i, t in enumerate(tiles):
        canvas.paste(Image.fromarray(t), (i * framing.width, title_h))
    if bar is not None:
        canvas.paste(bar, (width, title_h))
    if title:
        ImageDraw.Draw(canvas).text((10, int(title_h * 0.2)), title, fill=(0, 0, 0),
                                    font=text_font(max(12, int(title_h * 0.55))))
    return canvas


def render_distance_png(path: str | os.PathLike, mesh: MeshLike, reference: Optional[np.ndarray] = None,
                        **kwargs: Any) -> None:
    """Write :func:`render_distance_image` to ``path`` (PNG, atomically)."""
    atomic_write_bytes(path, png_bytes(render_distance_image(mesh, reference, **kwargs)))


def render_grid_image(meshes: Mapping[str, Optional[MeshLike]], reference: Optional[np.ndarray],
                      views: Sequence[str | tuple[float, float]] = ("front", "back"),
                      tile_height: int = 360, vmax: float = DEFAULT_VMAX_MM, up_axis: Optional[int] = None,
                      ground_truth: Optional[MeshLike] = None,
                      means_mm: Optional[Mapping[str, Optional[float]]] = None):
    """A PIL image: one column per method (``None`` mesh = "failed"), one row per view, the same
    camera and scale for all, one colour bar. ``ground_truth`` adds a grey first column; under each
    method's name the mean distance (or ``means_mm[name]``, e.g. its CD)."""
    Image, ImageDraw, _ = pil()
    cols: list[tuple[str, Optional[Colored]]] = []
    if ground_truth is not None:
        cols.append(("ground truth", colour_mesh(ground_truth, None, "ground truth")))
    for name, m in meshes.items():
        cols.append((name, None if m is None else colour_mesh(m, reference, name)))
    drawn = [c for _, c in cols if c is not None]
    if not drawn:
        raise InputError("nothing to render: every method failed")
    # frame on the reconstructions (the ground truth may be the whole merged CT model)
    recon = [c for (n, c) in cols if c is not None and not (ground_truth is not None and n == "ground truth")]
    every = np.concatenate([c.vertices for c in (recon or drawn)])
    if up_axis is None:
        finite = every[np.isfinite(every).all(axis=1)]
        up_axis = int(np.argmax(np.ptp(finite, axis=0)))
    cams = [camera(v, up_axis) for v in views]
    framing = frame(every, cams, tile_height)
    head_h = int(54 * max(0.75, tile_height / 360))
    font = text_font(int(16 * max(0.75, tile_height / 360)))
    bar = _colour_bar(framing.height * len(cams) + head_h, vmax, None, scale=max(0.75, tile_height / 360))
    heads = []
    for name, c in cols:
        mean = None
        if c is not None and (name != "ground truth" or ground_truth is None):
            mean = (means_mm or {}).get(name, c.mean_mm)
        second = ("failed (no mesh)" if c is None else
                  f"mean {mean:.2f} mm" if mean is not None and not math.isnan(mean) else "")
        heads.append((name, second))
    # a column is as wide as its header: a tall, thin bone would otherwise run the labels together
    width = max([framing.width] + [int(font.getlength(t)) + 16 for head in heads for t in head])
    canvas = Image.new("RGB", (width * len(cols) + bar.width, framing.height * len(cams) + head_h), BACKGROUND)
    draw = ImageDraw.Draw(canvas)
    for j, ((name, c), (_, second)) in enumerate(zip(cols, heads)):
        x = j * width
        draw.text((x + 8, 6), name, fill=(0, 0, 0), font=font)
        draw.text((x + 8, head_h // 2 + 2), second, fill=(180, 0, 0) if c is None else (40, 40, 40), font=font)
        if c is None:
            continue
        for i, cam in enumerate(cams):
            tile = render_view(c.vertices, c.faces, cam, framing, c.values, vmax)
            canvas.paste(Image.fromarray(tile), (x + (width - framing.width) // 2, head_h + i * framing.height))
    canvas.paste(bar, (width * len(cols), 0))
    return canvas


def render_grid_png(path: str | os.PathLike, meshes: Mapping[str, Optional[MeshLike]],
                    reference: Optional[np.ndarray], **kwargs: Any) -> None:
    """Write :func:`render_grid_image` to ``path`` (PNG, atomically)."""
    atomic_write_bytes(path, png_bytes(render_grid_image(meshes, reference, **kwargs)))
