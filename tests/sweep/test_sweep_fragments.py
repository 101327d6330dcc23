"""Isolated fragments of detections that neighbouring frames do not confirm."""

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.io import load_points
from ultraboneudf.sweep import Sweep, compound, sweep_to_points, unconfirmed_fragments, write_sweep
from ultraboneudf.sweep.transforms import rigid_from_euler

BONE_ROW, FASCIA_ROW, COLS = 30, 8, slice(5, 36)  # 0.5 mm pixels: bone 15 mm deep, fascia 4 mm
FASCIA = 18  # scan lines: enough points that the local outlier rule keeps the segment


def bone_sweep(n=30, frame_gap_mm=1.0, fascia_frames=(), fascia_cols=slice(12, 12 + FASCIA)):
    """Frames ``frame_gap_mm`` apart along z (image x → world x, beam → world y), a flat bone in
    every frame and a 2-pixel-thick fascia segment over it in ``fascia_frames``."""
    poses = np.stack([rigid_from_euler([0, 0, frame_gap_mm * i], [0, 0, 0]) for i in range(n)])
    masks = np.zeros((n, 40, 40), dtype=bool)
    masks[:, BONE_ROW, COLS] = True
    for f in fascia_frames:
        masks[f, FASCIA_ROW:FASCIA_ROW + 2, fascia_cols] = True
    return Sweep(image_to_world=poses, spacing_mm=0.5, image_size=(40, 40), masks=masks,
                 pixel_offset=0.5)


def bone_depth(cp):
    return np.isclose(cp.points[:, 1], (BONE_ROW + 0.5) * 0.5)


@pytest.mark.parametrize("frames", [(12,), (12, 13), (0,), (29,)])
def test_fragments_seen_in_one_or_two_frames_are_removed(frames):
    cp = compound(bone_sweep(fascia_frames=frames), top_only=True)
    fascia = ~bone_depth(cp)
    assert fascia.sum() == FASCIA * len(frames)  # top_only: the fascia hides the bone beneath it
    keep, report = unconfirmed_fragments(cp)
    np.testing.assert_array_equal(keep, ~fascia)
    assert (report.removed, report.fragments) == (FASCIA * len(frames), 1)


def test_a_structure_seen_in_three_frames_is_kept():
    cp = compound(bone_sweep(fascia_frames=(12, 13, 14)), top_only=True)
    keep, report = unconfirmed_fragments(cp)
    assert keep.all() and report.removed == 0
    keep, report = unconfirmed_fragments(cp, max_frames=3)
    assert report.removed == 3 * FASCIA


def test_frames_too_far_apart_do_not_judge():
    # frames 6 mm apart (a sparse subset of a sweep): every frame's bone is a group of its own and
    # nothing says the fascia is not there
    cp = compound(bone_sweep(n=8, frame_gap_mm=6.0, fascia_frames=(3,)), top_only=True)
    keep, report = unconfirmed_fragments(cp)
    assert keep.all() and report.groups >= 9
    # a reach beyond the frame gap links the frames, and the neighbours then judge the fascia
    keep, _ = unconfirmed_fragments(cp, reach_mm=8.0)
    np.testing.assert_array_equal(keep, bone_depth(cp))


def test_fragments_that_only_judge_each_other_are_all_kept():
    s = bone_sweep(n=2, fascia_frames=(0,))
    s.masks[1] = False
    s.masks[1, BONE_ROW, 30:36] = True  # frame 1 sees only a piece far from frame 0's fascia
    s.masks[0, BONE_ROW] = False
    cp = compound(s, top_only=True)
    keep, report = unconfirmed_fragments(cp)
    assert keep.all() and report.fragments == 0


def test_sweep_to_points_and_the_cli_remove_them(tmp_path, capsys):
    s = bone_sweep(fascia_frames=(12,))
    cp = sweep_to_points(s, segment="masks")
    assert bone_depth(cp).all() and len(cp) == 30 * 31 - FASCIA
    assert len(sweep_to_points(s, segment="masks", remove_fragments=False)) == 30 * 31
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    assert main(["sweep2points", str(tmp_path / "sw"), "-o", str(tmp_path / "a.xyz"), "--quiet"]) == 0
    assert len(load_points(tmp_path / "a.xyz")) == 30 * 31 - FASCIA
    assert main(["sweep2points", str(tmp_path / "sw"), "-o", str(tmp_path / "b.xyz"), "--quiet",
                 "--no-consistency"]) == 0
    assert len(load_points(tmp_path / "b.xyz")) == 30 * 31
    capsys.readouterr()
