"""Distance-coloured PNG renders: checked on properties of the images."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from ultraboneudf.evaluation import colormap, reference_points, render_distance_png, render_grid_png
from ultraboneudf.evaluation.render import BACKGROUND, Framing, camera, rasterize, render_view


def bumpy_sphere() -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    gt = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    n = gt.vertices / 20.0
    recon = trimesh.Trimesh(gt.vertices + n * (6.0 * np.clip(n[:, 2], 0, None) ** 4)[:, None], gt.faces,
                            process=False)
    return recon, gt


def non_background_fraction(img: np.ndarray) -> float:
    return float((np.abs(img.astype(int) - np.array(BACKGROUND)).sum(axis=-1) > 30).mean())


def test_rasterizer_covers_the_projected_area():
    # a 10×10 square seen from the front at 4 px/mm covers 40×40 = 1600 pixels
    v = np.array([[0, -5, -5], [0, 5, -5], [0, 5, 5], [0, -5, 5.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    cam = camera("front", up_axis=2)
    img = render_view(v, f, cam, Framing(centre=np.zeros(3), scale=4.0, width=64, height=64),
                      supersample=1)
    assert abs(int(non_background_fraction(img) * 64 * 64) - 1600) <= 80
    # the nearer of two overlapping triangles wins
    xy = np.array([[0, 0], [10, 0], [0, 10], [0, 0], [10, 0], [0, 10.0]])
    fb, _, _ = rasterize(xy, np.array([5, 5, 5, 1, 1, 1.0]), np.array([[0, 1, 2], [3, 4, 5]]), 12, 12)
    assert set(np.unique(fb[fb >= 0])) == {1}


def test_colormap_is_clamped_to_the_range():
    c = colormap(np.array([-1.0, 0.0, 2.5, 5.0, 50.0]), vmax=5.0)
    assert np.allclose(c[0], c[1]) and np.allclose(c[3], c[4])
    assert c[1][2] > c[1][0] and c[3][0] > c[3][2]  # blue at 0, red at the top


def test_distance_png_properties(tmp_path):
    recon, gt = bumpy_sphere()
    out = tmp_path / "r.png"
    render_distance_png(out, recon, reference_points(gt, samples=100_000), views=("front", "right", "top"),
                        tile_height=200, title="test")
    img = np.asarray(Image.open(out).convert("RGB"))
    assert img.shape[0] == 200 + int(200 * 0.08)
    assert img.shape[1] > 3 * 150
    tiles = img[16:, : img.shape[1] - 120]
    frac = non_background_fraction(tiles)
    assert 0.15 < frac < 0.9
    # the colour bar: a vertical ramp from red (top) to blue (bottom) right of the tiles
    bar = img[:, -120:]
    reds = np.argwhere((bar[..., 0] > 180) & (bar[..., 1] < 90) & (bar[..., 2] < 90))
    blues = np.argwhere((bar[..., 2] > 170) & (bar[..., 0] < 70))
    assert len(reds) > 20 and len(blues) > 20 and reds[:, 0].mean() < blues[:, 0].mean()
    # the bump on top is far from the ground truth (warm colours), the rest near it (blue)
    warm = (tiles[..., 0].astype(int) - tiles[..., 2].astype(int)) > 60
    cold = (tiles[..., 2].astype(int) - tiles[..., 0].astype(int)) > 60
    assert warm.sum() > 50 and cold.sum() > warm.sum()


def test_grid_png_with_a_failed_method(tmp_path):
    recon, gt = bumpy_sphere()
    out = tmp_path / "grid.png"
    render_grid_png(out, {"bumpy": recon, "exact": gt, "broken": None}, reference_points(gt, samples=50_000),
                    views=("front", "back"), tile_height=120, ground_truth=gt)
    img = np.asarray(Image.open(out).convert("RGB"))
    head = int(54 * 0.75)
    assert img.shape[0] == 2 * 120 + head
    col_w = (img.shape[1] - 90) // 4
    cols = [img[head:, i * col_w:(i + 1) * col_w] for i in range(4)]
    fracs = [non_background_fraction(c) for c in cols]
    assert all(f > 0.1 for f in fracs[:3]) and fracs[3] == 0.0  # the failed column is empty
    # the ground-truth column is grey (no distance colours)
    g = cols[0][np.abs(cols[0].astype(int) - 255).sum(-1) > 30].astype(int)
    assert np.abs(g[:, 0] - g[:, 2]).mean() < 12


def test_nothing_to_render_is_an_input_error(tmp_path):
    from ultraboneudf.errors import InputError

    with pytest.raises(InputError):
        render_grid_png(tmp_path / "x.png", {"a": None}, None)


def test_grid_columns_are_as_wide_as_their_labels_for_a_thin_bone(tmp_path):
    from ultraboneudf.pictures import text_font as _font

    rod = trimesh.creation.box(extents=(1.0, 1.0, 30.0))       # tall and thin: a narrow tile
    out = tmp_path / "grid.png"
    render_grid_png(out, {"first method": rod, "second method": rod}, rod.vertices, views=("front",),
                    tile_height=120, means_mm={"first method": 0.25, "second method": 0.5})
    img = np.asarray(Image.open(out).convert("RGB"))
    label = _font(12).getlength("second method")
    assert (img.shape[1] - 90) / 2 >= label + 16                 # two columns beside the 90 px bar
