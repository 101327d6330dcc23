"""Quality-control pictures of sweeps: marks and labels that survive the scaling to a contact sheet."""

import numpy as np

from ultraboneudf.sweep.figures import contact_sheet, mark_dilation, overlay

RED = np.array([255, 40, 40])


def _red_rows(tile: np.ndarray, column: int) -> int:
    """Rows of one column whose colour is close to the mask's red."""
    return int((np.abs(tile[:, column].astype(int) - RED).max(axis=1) < 60).sum())


def test_a_one_pixel_mask_stays_at_least_two_pixels_thick_on_the_sheet():
    frame = np.full((600, 800), 90, np.uint8)
    mask = np.zeros((600, 800), bool)
    mask[300, 100:700] = True                       # one pixel thick, the detector's output
    thin = np.asarray(contact_sheet([overlay(frame, mask, dilate=0)], tile_width=320))
    thick = np.asarray(contact_sheet([overlay(frame, mask, dilate=mark_dilation(800, 320))], tile_width=320))
    assert _red_rows(thin, 160) == 0                # blended away: what the sheets looked like
    assert _red_rows(thick, 160) >= 2
    assert mark_dilation(800, 320) == 3 and mark_dilation(200, 320) == 1


def test_labels_sit_on_a_dark_box_over_bright_tissue():
    white = np.full((400, 400), 255, np.uint8)
    sheet = np.asarray(contact_sheet([overlay(white, np.zeros_like(white, bool))], ["Seq_Frame0007"],
                                     tile_width=320))
    corner = sheet[:14, :60]
    assert (corner.sum(axis=2) == 0).mean() > 0.3            # the box behind the text
    yellow = (corner[..., 0] > 200) & (corner[..., 1] > 200) & (corner[..., 2] < 80)
    assert yellow.sum() > 20                                  # the text itself, in yellow
