"""Rigid-transform helpers and the starting poses users give (matrices, landmarks)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ultraboneudf.errors import InputError
from ultraboneudf.registration import pose_from_landmarks, read_init, rigid


def test_rotations_agree_and_invert():
    rng = np.random.default_rng(1)
    axes = rng.normal(size=(5, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([0.1, 0.7, 1.5, 2.5, 3.0])
    r = rigid.rotvec(axes * angles[:, None])
    assert np.allclose(r @ np.swapaxes(r, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(r), 1.0)
    assert np.allclose(rigid.rotation_angle_deg(r), np.degrees(angles))
    assert np.allclose(np.einsum("kij,kj->ki", r, axes), axes)          # the axis stays put
    assert np.allclose(rigid.axis_angle(axes, angles), r)
    t = rigid.homogeneous(r, rng.normal(size=(5, 3)))
    assert np.allclose(rigid.invert(t) @ t, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("a, b", [((0, 0, 1), (1, 0, 0)), ((0, 0, 1), (0, 0, 1)), ((0, 0, 1), (0, 0, -1)),
                                  ((1, 2, 3), (-3, 1, 0.5))])
def test_align_vectors_turns_a_onto_b(a, b):
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    r = rigid.align_vectors(a, b)
    assert np.allclose(r @ a, b, atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)


def test_fit_rigid_recovers_a_motion_and_never_mirrors():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3)) * 30
    truth = rigid.homogeneous(rigid.rotvec(np.array([0.3, -0.2, 1.1])), np.array([5.0, -40.0, 12.0]))
    assert np.allclose(rigid.fit_rigid(src, rigid.apply(truth, src)), truth, atol=1e-9)
    mirrored = src * np.array([1.0, 1.0, -1.0])
    assert np.linalg.det(rigid.fit_rigid(src, mirrored)[:3, :3]) > 0


def _landmarks():
    truth = rigid.homogeneous(rigid.rotvec(np.array([0.1, 0.5, -0.2])), np.array([10.0, 20.0, -5.0]))
    ct = np.array([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 25.0, 10.0], [5.0, 5.0, 60.0]])
    return truth, ct, rigid.apply(truth, ct)


def test_pose_from_three_landmark_pairs_is_exact():
    truth, ct, target = _landmarks()
    assert np.allclose(pose_from_landmarks(ct[:3], target[:3]), truth, atol=1e-9)


@pytest.mark.parametrize("kind", ["json_matrix", "json_transform", "json_landmarks", "txt_matrix", "txt_row16",
                                  "txt_landmarks", "npy_matrix", "npy_landmarks"])
def test_read_init_accepts_every_documented_form(tmp_path, kind):
    truth, ct, target = _landmarks()
    pairs = np.c_[ct, target]
    path = tmp_path / {"json": "init.json", "txt": "init.txt", "npy": "init.npy"}[kind.split("_")[0]]
    if kind == "json_matrix":
        path.write_text(json.dumps(truth.tolist()))
    elif kind == "json_transform":
        path.write_text(json.dumps({"kind": "ultraboneudf registration", "transform": truth.tolist()}))
    elif kind == "json_landmarks":
        path.write_text(json.dumps({"ct": ct.tolist(), "target": target.tolist()}))
    elif kind == "txt_matrix":
        np.savetxt(path, truth, header="CT to target")
    elif kind == "txt_row16":
        path.write_text(",".join(map(repr, truth.ravel().tolist())) + "\n")
    elif kind == "txt_landmarks":
        np.savetxt(path, pairs)
    elif kind == "npy_matrix":
        np.save(path, truth)
    else:
        np.save(path, pairs)
    pose, record = read_init(path)
    assert np.allclose(pose, truth, atol=1e-9)
    assert record["kind"] == ("landmarks" if "landmarks" in kind else "matrix")


@pytest.mark.parametrize("content, message", [
    ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not rigid"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], "not rigid"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "last row"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "expected"),
    ({"ct": [[0, 0, 0], [1, 0, 0]], "target": [[0, 0, 0], [1, 0, 0]]}, "at least 3"),
    ({"ct": [[0, 0, 0], [1, 0, 0], [2, 0, 0]], "target": [[0, 0, 0], [1, 0, 0], [2, 0, 0]]}, "one line"),
    ({"ct": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "target": [[0, 0, 0], [1, 0, 0]]}, "same number"),
    ({"points": []}, "needs"),
])
def test_read_init_refuses_bad_poses_naming_the_file(tmp_path, content, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputError, match=message) as err:
        read_init(path)
    assert "bad.json" in str(err.value)


def test_read_init_refuses_a_missing_or_unreadable_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_init(tmp_path / "nope.json")
    (tmp_path / "words.txt").write_text("four by four\n")
    with pytest.raises(InputError, match="words.txt"):
        read_init(tmp_path / "words.txt")
