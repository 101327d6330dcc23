"""The pixel → world chain: hand-computed examples, Euler round trips, rigidity checks."""

import numpy as np
import pytest

from ultraboneudf.errors import InputError
from ultraboneudf.sweep import Sweep
from ultraboneudf.sweep.transforms import (
    check_rigid,
    euler_from_rigid,
    invert_rigid,
    pixel_to_image_matrix,
    pixels_to_world,
    rigid_from_euler,
    split_scaled_transform,
)


def test_pixel_to_world_hand_computed():
    # T_track: rotate 90° about z, then translate (10, 20, 30); T_calib: translate (1, 2, 3).
    # Pixel (c, r) = (3, 5), s = 0.5 mm/px, centre offset 0.5:
    #   image mm     = (3.5·0.5, 5.5·0.5, 0) = (1.75, 2.75, 0)
    #   calib        → (2.75, 4.75, 3)
    #   Rz(90°)      → (−4.75, 2.75, 3)
    #   + (10,20,30) → (5.25, 22.75, 33)
    track = rigid_from_euler([10, 20, 30], [0, 0, 90])
    calib = rigid_from_euler([1, 2, 3], [0, 0, 0])
    sweep = Sweep(image_to_world=[track @ calib], spacing_mm=(0.5, 0.5), image_size=(8, 8),
                  pixel_offset=0.5)
    world = pixels_to_world(sweep.pixel_to_world()[0], np.array([3]), np.array([5]))
    np.testing.assert_allclose(world[0], [5.25, 22.75, 33.0], atol=1e-12)


def test_pixel_to_world_anisotropic_and_zero_offset():
    sweep = Sweep(image_to_world=[np.eye(4)], spacing_mm=(0.2, 0.1), image_size=(4, 4), pixel_offset=0.0)
    world = pixels_to_world(sweep.pixel_to_world()[0], np.array([0, 2]), np.array([0, 3]))
    np.testing.assert_allclose(world, [[0, 0, 0], [0.4, 0.3, 0]], atol=1e-15)


def test_stack_of_frames_with_frame_index():
    mats = np.stack([np.eye(4), rigid_from_euler([5, 0, 0], [0, 0, 0])])
    pts = pixels_to_world(mats, np.array([1.0, 1.0]), np.array([2.0, 2.0]), np.array([0, 1]))
    np.testing.assert_allclose(pts, [[1, 2, 0], [6, 2, 0]])


def test_euler_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(50):
        t = rng.uniform(-500, 500, 3)
        e = rng.uniform([-180, -89, -180], [180, 89, 180])
        m = rigid_from_euler(t, e)
        t2, e2 = euler_from_rigid(m)
        np.testing.assert_allclose(rigid_from_euler(t2, e2), m, atol=1e-12)


def test_euler_convention_is_extrinsic_xyz():
    # extrinsic x then y then z: R = Rz · Ry · Rx
    m = rigid_from_euler([0, 0, 0], [90, 0, 90])[:3, :3]
    rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(m, rz @ rx, atol=1e-12)


def test_invert_rigid():
    m = rigid_from_euler([3, -4, 5], [10, 20, 30])
    np.testing.assert_allclose(invert_rigid(m) @ m, np.eye(4), atol=1e-12)


def test_pixel_to_image_matrix():
    m = pixel_to_image_matrix((0.1, 0.2), 0.5)
    np.testing.assert_allclose(m @ [0, 0, 0, 1], [0.05, 0.1, 0, 1])


@pytest.mark.parametrize("bad, word", [
    (np.diag([1.0, 1.0, 1.02, 1.0]), "scaled or sheared"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "mirrored"),
    (np.vstack([np.eye(4)[:3], [0.1, 0, 0, 1]]), "last row must be 0 0 0 1"),
    (np.full((4, 4), np.nan), "NaN"),
    (np.eye(3), "4×4"),
])
def test_check_rigid_rejects(bad, word):
    with pytest.raises(InputError, match=word) as info:
        check_rigid(bad, "poses.csv: line 7")
    assert "poses.csv: line 7" in str(info.value)


def test_split_scaled_transform():
    rigid = rigid_from_euler([1, 2, 3], [10, -20, 30])
    m = rigid @ np.diag([0.1, 0.2, 7.0, 1.0])  # PLUS-style: scaling in the matrix, any z scale
    r, s = split_scaled_transform(m, "x.mha")
    np.testing.assert_allclose(s, [0.1, 0.2])
    np.testing.assert_allclose(r, rigid, atol=1e-12)


def test_split_scaled_transform_errors():
    with pytest.raises(InputError, match="no pixel spacing"):
        split_scaled_transform(np.diag([0.0, 1.0, 1.0, 1.0]), "a.mha")
    shear = np.eye(4)
    shear[0, 1] = 0.3
    with pytest.raises(InputError, match="sheared"):
        split_scaled_transform(shear, "a.mha")
