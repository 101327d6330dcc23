"""Frames and beams from a compounded cloud's order, on a bone mask imaged by a linear probe and
written pixel by pixel as a compounding writes it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ultraboneudf.geometry.frame_order import beams_from_order, frames_from_order

RADIUS = 12.0   # mm: a femoral shaft along x
LATERAL = 0.3   # mm: pixel spacing across the image
AXIAL = 0.08    # mm: pixel spacing down the beam


def mask_frames(count=15, rows_first=True, turn=None):
    """The band of pixels within 0.6 mm of the upper arc of a shaft (axis x), imaged by a probe
    above it looking down −z in planes x = const, each frame listed row by row from the probe down
    (``rows_first``) or column by column; the whole scene turned by ``turn``. Returns the frames'
    points and the true beam."""
    y = np.arange(-10.0, 10.0, LATERAL)
    z = np.arange(RADIUS + 0.8, RADIUS - 6.0, -AXIAL)   # from the probe down
    zz, yy = np.meshgrid(z, y, indexing="ij")           # rows (depth) first
    if not rows_first:
        zz, yy = zz.T, yy.T
    band = np.abs(np.hypot(yy, zz) - RADIUS) < 0.6
    frames = [np.column_stack([np.full(band.sum(), x), yy[band], zz[band]])
              for x in np.linspace(-30.0, 30.0, count)]
    beam = np.array([0.0, 0.0, -1.0])
    if turn is not None:
        frames = [turn.apply(f) for f in frames]
        beam = turn.apply(beam)
    return frames, beam


def test_each_frames_beam_and_side_come_from_its_rows():
    turn = Rotation.from_euler("xyz", [37, -21, 64], degrees=True)
    frames, beam = mask_frames(turn=turn)
    points = np.concatenate(frames)
    label = frames_from_order(points)
    assert len(np.unique(label[label >= 0])) == len(frames) and (label >= 0).all()
    beams = beams_from_order(points, label)
    assert np.all(beams @ beam > np.cos(np.radians(1.0)))  # every point's, its side included


def test_listed_from_the_far_end_the_beams_point_back():
    frames, beam = mask_frames()
    points = np.concatenate([f[::-1] for f in frames])
    beams = beams_from_order(points, frames_from_order(points))
    assert np.all(beams @ beam < -np.cos(np.radians(1.0)))


def test_another_order_tells_no_beam_along_the_beam():
    frames, beam = mask_frames(rows_first=False)
    points = np.concatenate(frames)
    beams = beams_from_order(points, frames_from_order(points))
    # listed column by column the "rows" run down the beam: what comes out lies across it
    told = np.any(beams != 0, axis=1)
    assert np.all(np.abs(beams[told] @ beam) < 0.05)
    shuffled = points[np.random.default_rng(0).permutation(len(points))]
    label = frames_from_order(shuffled)
    assert (label >= 0).mean() < 0.1
    assert not beams_from_order(shuffled, label).any()


@pytest.mark.parametrize("rows", [1, 2])
def test_a_frame_of_one_row_has_no_side(rows):
    y = np.arange(0.0, 6.0, LATERAL)
    frame = np.concatenate([np.column_stack([np.zeros(len(y)), y, np.full(len(y), -k * AXIAL)])
                            for k in range(rows)])
    beams = beams_from_order(frame, np.zeros(len(frame), dtype=int))
    if rows == 1:
        assert not beams.any()
    else:
        assert np.allclose(beams, [0.0, 0.0, -1.0])


def test_a_cloud_listed_along_its_echoes_curve_tells_no_beam():
    """One noisy echo per scan line across the shaft's upper arc, each frame listed from one side of
    the arc to the other (a cloud written along its curve, not row by row): its depth steps back up
    as much as down, and no point is told a beam; the same frames listed row by row all are."""
    rng = np.random.default_rng(0)
    y = np.arange(-10.0, 10.0, LATERAL)
    frames = [np.column_stack([np.full(len(y), x), y, np.sqrt(RADIUS**2 - y**2)])
              + rng.normal(0.0, 0.1, (len(y), 3)) * [0.0, 1.0, 1.0] for x in np.linspace(-30.0, 30.0, 15)]
    points = np.concatenate(frames)
    label = frames_from_order(points)
    assert (label >= 0).mean() > 0.9  # the frames are found
    assert not beams_from_order(points, label).any()
    rows, _ = mask_frames()
    rows = np.concatenate(rows)
    assert np.any(beams_from_order(rows, frames_from_order(rows)) != 0, axis=1).all()
