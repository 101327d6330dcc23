"""What is scored against a ground truth in another frame or unit is said before the scoring."""

import numpy as np

from ultraboneudf.evaluation.placement import placement_warnings


def _box(lo, hi, n=500, seed=0):
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3))


def test_a_short_scan_of_a_long_bone_is_not_flagged():
    femur = _box([0, 0, 0], [40, 40, 450])
    patch = _box([10, 10, 200], [30, 30, 230])   # 30 mm of the shaft: about 15× smaller
    assert placement_warnings(("ct.stl", femur), [("scan.xyz", patch)]) == []


def test_another_unit_and_another_frame_are_each_said_once():
    femur = _box([0, 0, 0], [40, 40, 450])
    metres = femur / 1000.0
    moved = femur + [0.0, 500.0, 0.0]
    lines = placement_warnings(("ct.stl", femur), [("m.ply", metres), ("far.ply", moved), ("ok.ply", femur)])
    assert len(lines) == 2
    assert lines[0].startswith("m.ply spans 0.453 mm and ct.stl 453 mm (1,000× apart)")
    assert lines[1].startswith("far.ply and ct.stl do not overlap (their bounding boxes lie 460 mm apart)")
