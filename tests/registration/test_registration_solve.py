"""``register``: known poses recovered from partial, one-sided, noisy views with false echoes, on
analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from reg_shapes import lumpy_bone, mean_error, motion, one_sided_view

import ultraboneudf
from ultraboneudf.errors import InputError
from ultraboneudf.registration import RegisterOptions, Registration, register, rigid
from ultraboneudf.registration.constraint import sensitivities
from ultraboneudf.registration.model import prepare_bone
from ultraboneudf.registration.search import distinct


@pytest.fixture(scope="module")
def bone():
    return lumpy_bone()


@pytest.fixture(scope="module")
def view(bone):
    return one_sided_view(bone)


@pytest.fixture(scope="module")
def moved(bone, view):
    """The view seen from a frame the CT is 40° and 45 mm away from: (target points, true CT → target)."""
    truth = motion(40.0, (1.0, -2.0, 0.5), (30.0, -20.0, 28.0), bone.centroid)
    return rigid.apply(truth, view), truth


@pytest.fixture(scope="module")
def found(bone, moved):
    return register(bone, moved[0], seed=0)


def test_the_view_is_partial_one_sided_and_polluted(bone, view):
    d = prepare_bone(bone).tree.query(view)[0]
    assert 0.25 < np.mean(d > 2.0) < 0.32                      # false echoes, as on real clouds
    seen = cKDTree(view[d < 1.0]).query(bone.vertices)[0] < 2.0
    assert 0.15 < seen.mean() < 0.4                              # 15–40% of the bone is seen



def test_a_far_pose_is_recovered_without_an_initial_pose(bone, moved, found):
    points, truth = moved
    assert isinstance(found, Registration)
    assert mean_error(found.transform, truth, bone) < 0.3
    assert np.allclose(found.transform @ found.inverse, np.eye(4), atol=1e-9)
    # what the result says about itself: the echoes are not explained, the bone is
    assert 0.65 < found.overlap < 0.76
    assert 0.15 < found.coverage < 0.45
    assert found.residual_mm < 0.6                               # noise σ = 0.3 mm
    assert found.confidence is not None and found.confidence > 0.1
    assert found.runner_up["distance_mm"] > 4.0 and found.runner_up["score"] < found.score
    assert found.hypotheses > 100_000


def test_an_initial_pose_is_refined_without_a_search(bone, moved):
    points, truth = moved
    nudge = motion(3.0, (0.0, 1.0, 1.0), (2.0, -1.5, 1.0), bone.centroid)
    reg = register(bone, points, init=truth @ nudge, seed=0)
    assert mean_error(reg.transform, truth, bone) < 0.5
    assert reg.confidence is None and reg.hypotheses == 0 and reg.init is not None


def test_a_mesh_target_is_registered_through_its_area_samples(bone):
    truth = motion(25.0, (0.0, 0.0, 1.0), (10.0, 0.0, -15.0), bone.centroid)
    faces = bone.faces[(bone.face_normals[:, 0] > 0.3)]
    patch = trimesh.Trimesh(rigid.apply(truth, bone.vertices), faces, process=False)
    reg = ultraboneudf.register(bone, patch, seed=1, anchors=3, turns=24)
    assert mean_error(reg.transform, truth, bone) < 0.3
    assert reg.overlap > 0.99


def test_the_json_record_holds_what_repeats_it(bone, moved, found):
    data = found.to_json()
    assert {"kind", "transform", "transform_target_to_ct", "rotation_deg", "translation_mm", "residual_mm",
            "inlier_mm", "overlap", "coverage", "score", "confidence", "runner_up", "weakest_motion",
            "hypotheses", "timings", "counts", "seed", "options", "init", "version", "input"} == set(data)
    assert data["kind"] == "ultraboneudf registration"
    assert np.allclose(np.array(data["transform"]), found.transform)
    assert set(data["timings"]) == {"prepare_s", "search_s", "refine_s", "total_s"}
    # the seed and the resolved options it records give the same pose again, to the bit
    again = register(bone, moved[0], seed=data["seed"], options=RegisterOptions.from_dict(data["options"]))
    assert np.array_equal(again.transform, found.transform)


def test_a_shaft_seen_without_its_ends_leaves_slide_and_roll_free():
    # a capped cylinder along z; the view: its side facing +x, away from the caps
    ct = trimesh.creation.cylinder(radius=12.0, height=200.0, sections=96)
    model = prepare_bone(ct)
    rng = np.random.default_rng(0)
    phi = rng.uniform(-0.6, 0.6, 3000)
    z = rng.uniform(-60.0, 60.0, 3000)
    view = np.c_[12.0 * np.cos(phi), 12.0 * np.sin(phi), z]
    values, vectors = sensitivities(model, view, 3.0, model.points[::50])
    assert values[0] < 0.01 and values[1] < 0.04 and values[2] > 0.15   # faceted: roll is felt a little
    slide, roll = vectors[:, 0], vectors[:, 1]       # (rotation vector, translation) per mm of displacement
    assert abs(slide[5]) > 0.99                         # a shift along the axis
    assert abs(roll[2]) > 20 * np.abs(roll[:2]).max()   # a turn about the axis
    assert abs(roll[2]) == pytest.approx(1 / np.sqrt(np.mean(np.sum(model.points[::50, :2] ** 2, axis=1))), rel=0.05)


def test_distinct_keeps_poses_apart():
    pts = np.random.default_rng(0).normal(size=(100, 3)) * 20
    shifts = [0.0, 0.5, 5.0, 5.2, 20.0]
    poses = rigid.homogeneous(np.broadcast_to(np.eye(3), (5, 3, 3)), np.array([[s, 0, 0] for s in shifts]))
    assert distinct(poses, pts, 1.0, 10).tolist() == [0, 2, 4]
    assert distinct(poses, pts, 1.0, 2).tolist() == [0, 2]


@pytest.mark.parametrize("target, message", [
    (np.zeros((50, 3)), "only 50 points"),
    (np.full((500, 3), np.nan), "NaN"),
    (np.random.default_rng(0).normal(size=(500, 3)) * 5000, "span"),
])
def test_bad_targets_are_refused(bone, target, message):
    with pytest.raises(InputError, match=message):
        register(bone, target)


def test_bad_options_are_refused(bone, view):
    with pytest.raises(InputError, match="unknown registration option"):
        register(bone, view, anchor=3)
    with pytest.raises(InputError, match="anchors"):
        register(bone, view, anchors=0)
    with pytest.raises(InputError, match="icp_cutoffs_mm"):
        register(bone, view, icp_cutoffs_mm="3,-1")
