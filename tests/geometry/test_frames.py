"""A sweep's image planes, and the data surface bridging the gaps between frames further than those
inside one."""

import numpy as np
import pytest

from ultraboneudf.geometry.frames import frame_axes
from ultraboneudf.geometry.data_surface import DataSurface
from ultraboneudf.geometry.surface_fit import fit_local_planes


def rotation(deg: float, axis: int) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def flat_sweep(xs, ys=np.arange(-10.0, 10.01, 0.25)):
    """A linear probe 20 mm above z = 0 imaging the plane x = const for each of ``xs`` (mm): its
    bone points (x, y, 0), their scan-line origins (x, y, 20) and frame numbers."""
    pts = np.concatenate([np.c_[np.full_like(ys, x), ys, np.zeros_like(ys)] for x in xs])
    origins = pts + [0.0, 0.0, 20.0]
    frames = np.repeat(np.arange(len(xs)), len(ys))
    return pts, origins, frames


def test_frame_axes_are_the_image_planes_normals_with_one_sign():
    pts, origins, frames = flat_sweep(np.arange(0.0, 10.0, 1.5))
    # each frame tilted by its own angle about z, some the other way round: still planes
    tilt = np.array([rotation(a, 2) for a in (0.0, 10.0, -20.0, 30.0, 5.0, -5.0, 15.0)])
    centre = np.array([[x, 0.0, 0.0] for x in np.arange(0.0, 10.0, 1.5)])
    pts = np.einsum("nij,nj->ni", tilt[frames], pts - centre[frames]) + centre[frames]
    origins = np.einsum("nij,nj->ni", tilt[frames], origins - centre[frames]) + centre[frames]
    axes = frame_axes(pts, origins, frames)
    expected = np.einsum("nij,j->ni", tilt[frames], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", axes, expected)), 1.0, atol=1e-9)
    assert (axes @ axes[0] > 0).all()                                   # one sign throughout


def test_frame_axes_are_zero_where_a_frame_spans_no_plane():
    pts, origins, frames = flat_sweep([0.0, 1.5])
    # frame 2: one point; frame 3: points and origins on a single line (one scan line)
    line = np.c_[np.full(5, 3.0), np.zeros(5), np.linspace(0.0, 4.0, 5)]
    pts = np.concatenate([pts, [[4.5, 0.0, 0.0]], line])
    origins = np.concatenate([origins, [[4.5, 0.0, 20.0]], line + [0.0, 0.0, 20.0]])
    frames = np.concatenate([frames, [2], np.full(5, 3)])
    axes = frame_axes(pts, origins, frames)
    assert np.abs(axes[frames < 2, 0]).min() == pytest.approx(1.0)
    assert not axes[frames >= 2].any()


def test_data_surface_bridges_a_run_of_lost_frames_but_not_a_gap_inside_the_frames():
    # frames every 1.5 mm along x, five lost between x = 6 and x = 15 (a 9 mm gap); inside every
    # frame the bone is missing for |y| < 5 (a 10 mm gap where the probe found no echo)
    xs = np.r_[np.arange(-6.0, 6.01, 1.5), np.arange(15.0, 27.01, 1.5)]
    ys = np.r_[np.arange(-14.0, -4.99, 0.25), np.arange(5.0, 14.01, 0.25)]
    pts, origins, frames = flat_sweep(xs, ys)
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    axes = frame_axes(pts, origins, frames)
    bridge = np.full(len(pts), 4.0)
    plain = DataSurface(pts, up, bridge)
    across = DataSurface(pts, up, bridge, frame_axis=axes, frame_order=frames, frame_bridge=10.0)
    short = DataSurface(pts, up, bridge, frame_axis=axes, frame_order=frames, frame_bridge=8.0)
    lost = np.array([[x, y, 0.3] for x in (7.0, 10.5) for y in (-10.0, 8.0)])  # over the lost frames
    rim = np.hypot(np.repeat([1.0, 4.5], 2), 0.3)                               # to the last frame
    inside = np.array([[x, 1.0, 0.3] for x in (-3.0, 0.0, 3.0)])               # over the gap inside
    np.testing.assert_allclose(across.distance(lost), 0.3, atol=1e-9)
    # the frame gap is longer than the ordinary bridge, and than an 8 mm frame bridge: open
    np.testing.assert_allclose(plain.distance(lost), rim, atol=1e-9)
    np.testing.assert_allclose(short.distance(lost), rim, atol=1e-9)
    # the gap inside the frames stays open with the frame bridge
    np.testing.assert_allclose(across.distance(inside), np.hypot(4.0, 0.3), atol=1e-9)
    # along the normal over the bridged gap: the height above the surface
    np.testing.assert_allclose(across.distances(lost)[1], 0.3, atol=1e-9)
    # a point with no plane bridges nothing, across frames neither
    bare = DataSurface(pts, np.zeros_like(pts), bridge, frame_axis=axes, frame_order=frames, frame_bridge=10.0)
    assert bare.distance(lost[:1])[0] == pytest.approx(np.hypot(1.0, 0.3))


def test_data_surface_does_not_bridge_over_a_frame_that_looked_and_found_no_bone():
    # the same 9 mm gap between x = 6 and x = 15, but a frame at x = 10.5 imaged it and found bone
    # only at its ends (|y| ≥ 12): the gap is seen and empty, not unseen
    xs = np.r_[np.arange(-6.0, 6.01, 1.5), np.arange(15.0, 27.01, 1.5)]
    pts, origins, frames = flat_sweep(xs)
    ys = np.r_[np.arange(-14.0, -11.99, 0.25), np.arange(12.0, 14.01, 0.25)]
    middle, middle_origins, _ = flat_sweep([10.5], ys)
    order = np.where(xs[frames] > 10.0, frames + 1, frames)              # the middle frame's place
    pts = np.concatenate([pts, middle])
    origins = np.concatenate([origins, middle_origins])
    order = np.concatenate([order, np.full(len(middle), int((xs < 10.0).sum()))])
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    surface = DataSurface(pts, up, np.full(len(pts), 4.0), frame_axis=frame_axes(pts, origins, order),
                          frame_order=order, frame_bridge=10.0)
    q = np.array([[7.0, 0.0, 0.3], [8.0, 5.0, 0.3]])
    np.testing.assert_allclose(surface.distance(q), np.hypot([1.0, 2.0], 0.3), atol=1e-9)


def test_data_surface_from_planes_takes_the_frame_axes_the_planes_carry():
    xs = np.r_[np.arange(-6.0, 6.01, 1.5), np.arange(15.0, 27.01, 1.5)]
    pts, origins, frames = flat_sweep(xs)
    planes = fit_local_planes(pts, 4.0)
    q = np.array([[7.0, 0.0, 0.3]])
    assert DataSurface.from_planes(pts, planes, 1.0, frame_bridge=2.5).distance(q)[0] > 0.9  # no axes
    import dataclasses

    planes = dataclasses.replace(planes, frame_axis=frame_axes(pts, origins, frames), frame_order=frames)
    assert DataSurface.from_planes(pts, planes, 1.0, frame_bridge=2.5).distance(q)[0] == pytest.approx(0.3)
    assert DataSurface.from_planes(pts, planes.subset(np.arange(len(pts))), 1.0,
                                   frame_bridge=2.5).distance(q)[0] == pytest.approx(0.3)
    assert DataSurface.from_planes(pts, planes, 1.0, frame_bridge=0.0).distance(q)[0] > 0.9


def test_the_rim_reach_stops_at_the_sweeps_first_and_last_image_planes():
    from ultraboneudf.geometry.frames import sweep_ends

    xs = np.arange(0.0, 9.01, 1.5)                                      # frames 0..6 along +x
    pts, origins, frames = flat_sweep(xs)
    axes = frame_axes(pts, origins, frames)
    ends = sweep_ends(pts, frames, axes)
    np.testing.assert_allclose(ends[frames == 0], np.tile([-1.0, 0.0, 0.0], ((frames == 0).sum(), 1)))
    np.testing.assert_allclose(ends[frames == 6], np.tile([1.0, 0.0, 0.0], ((frames == 6).sum(), 1)))
    assert not ends[(frames > 0) & (frames < 6)].any()
    assert not sweep_ends(pts[frames == 3], frames[frames == 3], axes[frames == 3]).any()  # one frame
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    bridge = np.full(len(pts), 4.0)
    q = np.array([[-1.0, 0.0, 0.3],     # 1 mm past the first frame, out of the sweep
                  [10.0, 0.0, 0.3],     # 1 mm past the last one
                  [4.5, 11.0, 0.3],     # 1 mm past the bone's lateral rim, inside the sweep
                  [-1.0, 11.0, 0.3]])   # past both: the lateral part is reached, the outward not
    cut = DataSurface(pts, up, bridge, reach=2.0, frame_end=ends)
    np.testing.assert_allclose(cut.distance(q), [np.hypot(1.0, 0.3), np.hypot(1.0, 0.3), 0.3,
                                                 np.hypot(1.0, 0.3)], atol=1e-9)
    free = DataSurface(pts, up, bridge, reach=2.0)                      # without the sweep's ends
    np.testing.assert_allclose(free.distance(q), 0.3, atol=1e-9)
