"""The picture basics: colour ramps, PNG palettes, the file format chosen by the suffix."""

import io

import numpy as np
from PIL import Image

from ultraboneudf.pictures import MARKER_COLOURS, png_bytes, ramp, save_picture

STOPS = ((0.0, (0, 0, 0)), (0.25, (200, 0, 0)), (1.0, (200, 200, 100)))


def test_ramp_passes_through_its_stops_and_clamps():
    got = ramp(np.array([-1.0, 0.0, 0.25, 1.0, 7.0]), STOPS)
    assert got.shape == (5, 3)
    np.testing.assert_allclose(got, [[0, 0, 0], [0, 0, 0], [200, 0, 0], [200, 200, 100], [200, 200, 100]])


def test_ramp_is_linear_between_stops_on_any_shape():
    t = np.array([[0.125, 0.625]])
    np.testing.assert_allclose(ramp(t, STOPS), [[[100, 0, 0], [200, 100, 50]]])


def test_grey_palette_keeps_marker_colours_exact():
    rgb = np.full((8, 8, 3), 97, dtype=np.uint8)
    for k, c in enumerate(MARKER_COLOURS):
        rgb[k, :] = c
    back = np.asarray(Image.open(io.BytesIO(png_bytes(Image.fromarray(rgb), greys=16))).convert("RGB"))
    for k, c in enumerate(MARKER_COLOURS):
        assert (back[k] == c).all()
    grey = back[6, 0]
    assert grey[0] == grey[1] == grey[2] and abs(int(grey[0]) - 97) <= 255 / 15 / 2 + 1


def test_save_picture_writes_the_format_of_the_suffix(tmp_path):
    image = Image.fromarray(np.zeros((4, 4, 3), dtype=np.uint8))
    save_picture(image, tmp_path / "a.png")
    save_picture(image, tmp_path / "a.JPG")
    assert Image.open(tmp_path / "a.png").format == "PNG"
    assert Image.open(tmp_path / "a.JPG").format == "JPEG"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.JPG", "a.png"]   # nothing half-written left
