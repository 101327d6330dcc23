"""Quality-control pictures for sweeps (Pillow only): segmentation overlays, contact sheets and
a point-cloud splat render. Used by ``sweep2points --overlays`` and the docs figures; written with
:func:`~ultraboneudf.pictures.save_picture`."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw
from scipy.ndimage import maximum_filter

from ..pictures import ramp, text_font

FRAME_STOPS = ((0.0, (68, 1, 84)), (0.25, (59, 82, 139)), (0.5, (33, 145, 140)), (0.75, (94, 201, 98)),
               (1.0, (253, 231, 37)))
"""A viridis-like ramp for colouring by frame index (dark → light)."""


def mark_dilation(image_width: int, tile_width: int) -> int:
    """The ``dilate`` of :func:`overlay` that keeps a one-pixel mask at least two pixels thick once
    a frame ``image_width`` pixels wide is scaled to a tile ``tile_width`` wide."""
    return max(1, math.ceil(image_width / max(tile_width, 1)))


def overlay(image: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int] = (255, 40, 40),
            truth: np.ndarray | None = None, dilate: int = 1) -> Image.Image:
    """RGB picture of a grey frame with ``mask`` drawn in ``colour`` (and ``truth`` in green).

    ``dilate`` thickens the drawn marks by that many pixels each way (:func:`mark_dilation` picks it
    for a contact sheet) so thin masks stay visible after down-scaling.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(img.astype(np.float64) / max(float(img.max()), 1.0) * 255, 0, 255).astype(np.uint8)
    rgb = np.repeat(img[..., None], 3, axis=2).copy()

    def thick(m: np.ndarray) -> np.ndarray:
        m = np.asarray(m, dtype=bool)
        return maximum_filter(m, size=2 * dilate + 1) if dilate > 0 else m

    if truth is not None:
        rgb[thick(truth)] = (40, 220, 60)
    rgb[thick(mask)] = colour
    return Image.fromarray(rgb)


def contact_sheet(tiles: Sequence[Image.Image], labels: Sequence[str] | None = None,
                  columns: int = 5, tile_width: int = 320) -> Image.Image:
    """Grid of pictures scaled to ``tile_width`` pixels wide, each with an optional label (on a dark
    box, so it reads over bright tissue)."""
    font = text_font(max(11, min(18, tile_width // 20)))
    scaled = []
    for k, t in enumerate(tiles):
        h = max(1, round(t.size[1] * tile_width / t.size[0]))
        im = t.convert("RGB").resize((tile_width, h), Image.LANCZOS)
        if labels is not None:
            d = ImageDraw.Draw(im)
            box = d.textbbox((4, 3), str(labels[k]), font=font)
            d.rectangle((box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2), fill=(0, 0, 0))
            d.text((4, 3), str(labels[k]), fill=(255, 255, 0), font=font)
        scaled.append(im)
    th = max(im.size[1] for im in scaled)
    rows = (len(scaled) + columns - 1) // columns
    sheet = Image.new("RGB", (columns * tile_width, rows * th), (0, 0, 0))
    for k, im in enumerate(scaled):
        sheet.paste(im, ((k % columns) * tile_width, (k // columns) * th))
    return sheet


def _splat(u: np.ndarray, v: np.ndarray, depth: np.ndarray, colours: np.ndarray,
           size: tuple[int, int], point_px: int) -> np.ndarray:
    """Draw points at pixel coordinates ``(u, v)``, nearest (largest ``depth``) on top, shaded."""
    w, h = size
    img = np.zeros((h, w, 3))
    order = np.argsort(depth)
    shade = 0.5 + 0.5 * (depth - depth.min()) / max(float(np.ptp(depth)), 1e-12)
    col = np.clip(colours * shade[:, None], 0, 255)[order]
    xi, yi = np.rint(u[order]).astype(int), np.rint(v[order]).astype(int)
    for dx in range(point_px):
        for dy in range(point_px):
            xx, yy = xi + dx, yi + dy
            ok = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            img[yy[ok], xx[ok]] = col[ok]
    return img.astype(np.uint8)


def render_points(points: np.ndarray, values: np.ndarray | None = None, width: int = 1000,
                  panel_height: int = 240, point_px: int = 2, title: str = "",
                  max_exaggeration: float = 12.0) -> Image.Image:
    """Orthographic splat render of a point cloud (mm), three panels stacked.

    With principal axes ``a1`` (longest), ``a2``, ``a3`` of the cloud: the top panel looks along
    ``a3`` (the cloud's face), the middle along ``a2`` (its profile), both with ``a1`` horizontal;
    their vertical axis may be stretched (labelled "vertical ×k") so long thin strips stay
    readable. The bottom panel is the cross-section seen along ``a1`` at true scale. Points are
    coloured by ``values`` (e.g. frame index, dark → light) and shaded by depth; 10 mm scale bars.
    """
    pts = np.asarray(points, dtype=np.float64)
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred[:: max(1, len(pts) // 100_000)], full_matrices=False)
    q = centred @ vt.T
    lo, hi = np.percentile(q, 0.2, axis=0), np.percentile(q, 99.8, axis=0)
    ext = np.maximum(hi - lo, 1e-6)
    mid = (hi + lo) / 2
    t = np.zeros(len(pts)) if values is None else np.asarray(values, dtype=np.float64)
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-12)
    colours = np.rint(ramp(t, FRAME_STOPS))
    margin = 24
    panels = []
    for a_v, a_d, name in ((1, 2, "face (along a3)"), (2, 1, "profile (along a2)")):
        s_u = (width - 2 * margin) / ext[0]
        s_v = (panel_height - 2 * margin) / ext[a_v]
        if s_v < s_u:
            s_u = s_v
        s_v = min(s_v, s_u * max_exaggeration)
        u = (q[:, 0] - mid[0]) * s_u + width / 2
        v = -(q[:, a_v] - mid[a_v]) * s_v + panel_height / 2
        panel = Image.fromarray(_splat(u, v, q[:, a_d], colours, (width, panel_height), point_px))
        d = ImageDraw.Draw(panel)
        exag = s_v / s_u
        label = name + (f", vertical x{exag:.1f}" if exag > 1.05 else "")
        d.text((8, 6), label, fill=(200, 200, 200))
        y0 = panel_height - 12
        d.line([(margin, y0), (margin + 10 * s_u, y0)], fill=(255, 255, 255), width=3)
        d.text((margin, y0 - 14), "10 mm", fill=(255, 255, 255))
        panels.append(panel)
    # cross-section at true scale
    s_c = min((width / 2 - 2 * margin) / ext[1], (panel_height * 1.5 - 2 * margin) / ext[2])
    ch = int(panel_height * 1.5)
    u = (q[:, 1] - mid[1]) * s_c + width / 2
    v = -(q[:, 2] - mid[2]) * s_c + ch / 2
    panel = Image.fromarray(_splat(u, v, q[:, 0], colours, (width, ch), point_px))
    d = ImageDraw.Draw(panel)
    d.text((8, 6), "cross-section (along a1), true scale", fill=(200, 200, 200))
    d.line([(margin, ch - 12), (margin + 10 * s_c, ch - 12)], fill=(255, 255, 255), width=3)
    d.text((margin, ch - 26), "10 mm", fill=(255, 255, 255))
    panels.append(panel)
    out = Image.new("RGB", (width, sum(p.size[1] for p in panels) + 2 * (len(panels) - 1)), (60, 60, 60))
    y = 0
    for p in panels:
        out.paste(p, (0, y))
        y += p.size[1] + 2
    if title:
        ImageDraw.Draw(out).text((width - 8 - 7 * len(title), 6), title, fill=(255, 255, 255))
    return out


def mesh_section_pixels(mesh, pixel_to_world: np.ndarray) -> np.ndarray:
    """The mesh's cut by one frame's image plane, as ``(K, 2, 2)`` segments in that frame's pixel
    coordinates ``(column, row)`` (empty when the plane misses the mesh)."""
    from trimesh.intersections import mesh_plane

    normal = pixel_to_world[:3, 2] / np.linalg.norm(pixel_to_world[:3, 2])
    segs = mesh_plane(mesh, normal, pixel_to_world[:3, 3])
    if len(segs) == 0:
        return np.zeros((0, 2, 2))
    w2p = np.linalg.inv(pixel_to_world)
    pix = segs.reshape(-1, 3) @ w2p[:3, :3].T + w2p[:3, 3]
    return pix[:, :2].reshape(-1, 2, 2)


def frames_with_mesh(sweep, masks: np.ndarray, mesh, frames: Sequence[int], columns: int = 3,
                     tile_width: int = 360, crop: tuple[int, int, int, int] | None = None) -> Image.Image:
    """Contact sheet of frames with the detected bone (red: the pixels that became points) and the
    reconstructed mesh cut by each frame's plane (green), so a reader sees whether the surface
    follows the echo. ``crop`` = ``(column, row, width, height)`` of the frames to show."""
    p2w = sweep.pixel_to_world()
    shown = crop[2] if crop is not None else sweep.width
    dilate = mark_dilation(shown, tile_width)
    tiles = []
    for i in frames:
        im = overlay(sweep.images[i], masks[i], dilate=dilate)
        d = ImageDraw.Draw(im)
        width = 2 * dilate + 1
        for (a, b) in mesh_section_pixels(mesh, p2w[i]):
            d.line([tuple(a), tuple(b)], fill=(60, 230, 90), width=width)
        if crop is not None:
            im = im.crop((crop[0], crop[1], crop[0] + crop[2], crop[1] + crop[3]))
        tiles.append(im)
    return contact_sheet(tiles, [sweep.frame_names[i] for i in frames], columns=columns, tile_width=tile_width)
