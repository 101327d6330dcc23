"""Points an outlier rule removed, given back when the sweep confirms them."""

import numpy as np

from ultraboneudf.sweep.compound import CompoundedPoints
from ultraboneudf.sweep.consistency import confirmed_by_frames
from ultraboneudf.sweep.outliers import outlier_mask
from ultraboneudf.sweep.points import drop_outliers

BONE_DEPTH = 15.0  # mm below the probe face (y = 0); the beams run along +y; frames 1 mm apart in z
WALL = ((15.8, 17.5), (16.2, 20.0), (16.6, 22.5))  # (x, depth) mm: a face about 80° from the beam


def sweep_points(wall_frames=range(5, 10), shadow_frames=range(10, 15), flicker_frames=(3, 4)):
    """A flat bone top (x 0–15 mm, 0.2 mm apart) in 20 frames, a steep wall beside it seen sparsely
    in ``wall_frames``, false echoes 4 mm under the top in ``shadow_frames``, an echo over nothing
    in ``flicker_frames`` and one lone echo. Returns the points and the label of each."""
    xyz, frames, labels = [], [], []

    def add(x, depth, frame, label):
        xyz.append((x, depth, float(frame)))
        frames.append(frame)
        labels.append(label)

    for f in range(20):
        for x in np.arange(0.0, 15.0, 0.2):
            add(x, BONE_DEPTH, f, "bone")
    for f in wall_frames:
        for x, depth in WALL:
            add(x, depth, f, "wall")
    for f in shadow_frames:
        add(5.0, BONE_DEPTH + 4.0, f, "shadow")
    for f in flicker_frames:
        add(25.0, 10.0, f, "flicker")
    add(30.0, 12.0, 17, "lone")
    pts = np.asarray(xyz)
    beam = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    probe = pts * [1.0, 0.0, 1.0]
    cp = CompoundedPoints(pts, np.asarray(frames), probe, beam, np.zeros((len(pts), 2)))
    return cp, np.asarray(labels)


def test_only_the_unshadowed_points_seen_in_three_frames_come_back():
    cp, label = sweep_points()
    removed = label != "bone"
    back = confirmed_by_frames(cp, removed)
    np.testing.assert_array_equal(back, label == "wall")
    # the wall is seen in five frames: asking for six gives nothing back
    assert not confirmed_by_frames(cp, removed, min_frames=6).any()
    # the same wall in two frames only is a fragment, not a confirmed face
    cp2, label2 = sweep_points(wall_frames=(5, 6))
    assert not confirmed_by_frames(cp2, label2 != "bone").any()


def test_echoes_under_the_kept_bone_stay_removed_whatever_their_frame_count():
    cp, label = sweep_points(shadow_frames=range(0, 20))
    back = confirmed_by_frames(cp, label == "shadow")
    assert not back.any()
    # without the bone above them (removed too) they are no longer in its shadow
    back = confirmed_by_frames(cp, label != "wall")
    assert back[label == "shadow"].all()


def test_nothing_removed_or_everything_removed_gives_nothing_back():
    cp, label = sweep_points()
    assert not confirmed_by_frames(cp, np.zeros(len(cp), dtype=bool)).any()
    assert not confirmed_by_frames(cp, np.ones(len(cp), dtype=bool)).any()


def test_drop_outliers_keeps_the_steep_wall_the_local_rule_removes():
    cp, label = sweep_points()
    plain = outlier_mask(cp.points)
    assert not plain[label == "wall"].all()  # the local outlier factor alone loses part of the wall
    assert not plain[label == "shadow"].any()
    kept = drop_outliers(cp)
    assert len(kept) == int((plain | (label == "wall")).sum())
    assert (kept.points[:, 0] > 15.5).sum() == 3 * 5  # every wall point
    assert not np.any(np.isclose(kept.points[:, 1], BONE_DEPTH + 4.0))  # no shadowed echo
