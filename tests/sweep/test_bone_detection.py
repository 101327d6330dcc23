"""The classical detector's sweep-level behaviour: the deepest strong echo (not the first bright
line), no bone in water, the imaged region of screen-captured frames, per-frame confidence, and
the frame-to-frame consistency filter."""

import numpy as np

from ultraboneudf.sweep import BoneDetector, Sweep
from ultraboneudf.sweep.bone import classical_bone_masks
from ultraboneudf.sweep.consistency import consistent_detections
from ultraboneudf.sweep.segment import imaged_region
from ultraboneudf.sweep.transforms import rigid_from_euler

SPACING = 0.1


def to_uint8(img):
    return np.clip(255 * np.log1p(8 * img) / np.log1p(8 * 2.5), 0, 255).astype(np.uint8)


def fascia_over_muscle_over_bone(seed=0, h=300, w=300):
    """Tissue speckle; a bright fascia at row 50 over a hypoechoic muscle band (rows 53-150): a
    bright line with a dark band below, like a bone echo to a first-bright-line detector; the bone
    echo at row 170 (columns 60-240) with its acoustic shadow."""
    rng = np.random.default_rng(seed)
    y = np.arange(h)[:, None]
    img = 0.35 * rng.rayleigh(1.0, (h, w)) / 1.25
    img[53:150] *= 0.12
    img += 1.4 * np.exp(-0.5 * ((y - 50) / 1.5) ** 2)
    bone = (np.arange(w) >= 60) & (np.arange(w) <= 240)
    img *= np.where(bone[None, :] & (y > 173), 0.06, 1.0)
    img += np.where(bone[None, :], 1.6 * np.exp(-0.5 * ((y - 170) / 2.0) ** 2), 0.0)
    return to_uint8(img), bone


def test_deepest_strong_echo_is_the_bone_not_the_fascia_above():
    img, bone = fascia_over_muscle_over_bone()
    det = BoneDetector().detect(img, SPACING)
    found = np.isfinite(det.rows)
    assert found[bone].mean() > 0.9
    assert np.abs(det.rows[bone & found] - 170).max() <= 3          # within 0.3 mm of the bone
    assert 0.1 < det.confidence <= 1.0 and det.tissue_ratio > 0.1


def test_water_bath_has_no_bone():
    """An N-wire phantom in water: bright wire echoes (4 mm wide, smeared by the beam), the
    water black (0) above and below them, as the scanner shows it."""
    from scipy import ndimage

    img = np.zeros((300, 300))
    for r, c in [(80, 60), (80, 150), (80, 240), (140, 100), (140, 200)]:
        img[r - 2:r + 2, c - 20:c + 20] = 2.0
    img = to_uint8(ndimage.gaussian_filter(img, 1.0))
    img[img < 3] = 0
    det = BoneDetector().detect(img, SPACING)
    assert not np.isfinite(det.rows).any() and det.confidence == 0.0
    assert det.tissue_ratio < BoneDetector().min_tissue_ratio


def test_imaged_region_of_a_screen_capture():
    frames = np.zeros((3, 60, 80), dtype=np.uint8)
    frames[:, 5:55, 20:70] = 50
    assert imaged_region(frames) == (20, 5, 50, 50)
    img, bone = fascia_over_muscle_over_bone(h=300, w=300)
    framed = np.zeros((340, 400), dtype=np.uint8)
    framed[20:320, 50:350] = img                   # black border: its edges are not echoes
    det = BoneDetector().detect(framed, SPACING, region=(50, 20, 300, 300))
    found = np.isfinite(det.rows)
    assert not found[:50].any() and not found[350:].any()
    assert np.abs(det.rows[50:350][bone & found[50:350]] - 190).max() <= 3


def parallel_sweep(n, step_mm, w=40, h=30, spacing=0.5):
    poses = np.stack([rigid_from_euler([0, 0, step_mm * i], [0, 0, 0]) for i in range(n)])
    return Sweep(image_to_world=poses, spacing_mm=spacing, image_size=(w, h), pixel_offset=0.0)


def test_consistency_filter_drops_an_echo_no_neighbour_continues():
    s = parallel_sweep(10, 0.5)
    rows = np.full((10, 40), 12.0)
    rows[5, 10:20] = 25.0               # a flicker 6.5 mm deeper, in one frame only
    rows[:, 35:] = np.nan
    out, rep = consistent_detections(s, rows)
    assert np.isnan(out[5, 10:20]).all() and rep.removed == 10
    np.testing.assert_array_equal(out[np.arange(10) != 5], rows[np.arange(10) != 5])
    np.testing.assert_array_equal(out[5, 20:35], 12.0)
    assert rep.frames_judged == 10
    # frames 20 mm apart: no neighbour can judge, nothing is removed
    far = parallel_sweep(10, 20.0)
    out, rep = consistent_detections(far, rows)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(rows))
    assert rep.judged == 0 and rep.removed == 0


def test_classical_bone_masks_report():
    img, bone = fascia_over_muscle_over_bone()
    frames = np.stack([np.roll(img, 0, axis=0)] * 6)
    s = Sweep(image_to_world=np.stack([rigid_from_euler([0, 0, 0.3 * i], [0, 0, 0]) for i in range(6)]),
              spacing_mm=SPACING, image_size=(300, 300), images=frames, pixel_offset=0.0)
    masks, rep = classical_bone_masks(s)
    assert rep.frames_with_bone == 6 and rep.no_tissue_frames == 0
    assert masks.shape == (6, 300, 300) and masks.sum(axis=1).max() == 1
    rows = np.argmax(masks, axis=1)[:, bone]
    assert np.abs(rows - 170).max() <= 3
    assert rep.as_dict()["consistency"]["removed"] == 0
