"""False echoes in front of the bone and detached clusters, on a cylinder (a long bone), a thin
plate seen from both sides (the iliac wing) and a sweep's beams."""

import numpy as np

from ultraboneudf.geometry.echo_layers import false_echoes, front_orientation, small_components
from ultraboneudf.geometry.surface_fit import fit_local_planes

RADIUS = 12.0  # mm: a femoral shaft


def shaft(n=30_000, noise=0.5, seed=0, half_angle=100.0, length=80.0):
    """Points of the upper part of a cylinder of radius ``RADIUS`` along x (the side a probe sees,
    ±``half_angle`` degrees from +z), ``noise`` mm across the surface; and their outward normals."""
    rng = np.random.default_rng(seed)
    a = np.radians(rng.uniform(-half_angle, half_angle, n))
    normal = np.c_[np.zeros(n), np.sin(a), np.cos(a)]
    pts = np.c_[rng.uniform(-length / 2, length / 2, n), np.zeros((n, 2))] + \
        normal * (RADIUS + rng.normal(0.0, noise, n))[:, None]
    return pts, normal


def soft_tissue(seed=1):
    """What real segmentations add in front of a shaft: a sheet 8 mm over it (600 points over
    30 × 16 mm: a third of the bone's density), streaks rising from it along the normal, and a
    cluster floating beyond the end of the shaft, over no bone and off the plane of its surface."""
    rng = np.random.default_rng(seed)
    x, a = rng.uniform(-15, 15, 600), np.radians(rng.uniform(-35, 35, 600))
    sheet = np.c_[x, (RADIUS + 8.0) * np.sin(a), (RADIUS + 8.0) * np.cos(a)]
    streaks = []
    for k in range(12):
        x0, a0 = rng.uniform(-35, 35), np.radians(rng.uniform(-60, 60))
        r = np.linspace(RADIUS + 4.0, RADIUS + 18.0, 40)
        streaks.append(np.c_[np.full(40, x0), r * np.sin(a0), r * np.cos(a0)])
    cluster = np.c_[rng.normal(55, 1.5, 150), rng.normal(0, 1.5, 150), rng.normal(RADIUS + 20, 1.0, 150)]
    return sheet, np.concatenate(streaks), cluster


def test_a_cylinder_is_oriented_outward_by_its_convexity():
    pts, normal = shaft(n=8_000)
    flipped = normal * np.where(np.random.default_rng(2).random(len(pts)) < 0.5, -1.0, 1.0)[:, None]
    front = front_orientation(pts, flipped, 20.0, 4.0)
    assert np.mean(np.einsum("ij,ij->i", front, normal) > 0) > 0.99


def test_sheets_streaks_and_clusters_in_front_of_a_shaft_are_dropped_and_the_shaft_kept():
    bone, _ = shaft()
    sheet, streaks, cluster = soft_tissue()
    cloud = np.r_[bone, sheet, streaks, cluster]
    n, s, t = len(bone), len(sheet), len(streaks)
    planes = fit_local_planes(cloud, 4.0)
    drop = false_echoes(cloud, planes, None, depth=30.0, ratio=2.0, fraction=0.02)
    assert drop[:n].mean() < 0.01
    assert drop[n:n + s].mean() > 0.95
    # a streak's foot, within the band a column leaves as its own, may stay
    assert drop[n + s:n + s + t].mean() > 0.8
    assert drop[n + s + t:].all()
    # without the rules nothing is dropped; the component rule alone drops the cluster, no column
    # reaches it
    assert not false_echoes(cloud, planes, None, depth=0.0, ratio=2.0, fraction=0.0).any()
    alone = false_echoes(cloud, planes, None, depth=0.0, ratio=2.0, fraction=0.02)
    assert alone[n + s + t:].all() and not alone[:n].any()


def test_a_sheet_behind_the_bone_and_both_faces_of_a_thin_plate_are_kept():
    """Echoes behind a layer are not judged: a thin plate of bone (6 mm thick, as the iliac wing)
    scanned from both sides has each face behind the other."""
    rng = np.random.default_rng(3)
    n = 12_000
    y, x = rng.uniform(-30, 30, n), rng.uniform(-30, 30, n)
    side = np.where(rng.random(n) < 0.5, 3.0, -3.0)
    # two faces of a plate in z = ±3 mm, joined by a rounded rim at y > 30 (the crest)
    a = np.radians(rng.uniform(-90, 90, n // 3))
    crest = np.c_[rng.uniform(-30, 30, n // 3), 30 + 3.0 * np.cos(a), 3.0 * np.sin(a)]
    plate = np.r_[np.c_[x, y, side + rng.normal(0, 0.3, n)], crest]
    planes = fit_local_planes(plate, 4.0)
    drop = false_echoes(plate, planes, None, depth=30.0, ratio=2.0, fraction=0.02)
    assert drop.mean() < 0.01


def test_with_probe_positions_the_front_is_the_probes_side():
    """A sweep looking down −z at a plane: a fainter sheet 6 mm above it (toward the probe) is
    dropped; the same sheet 6 mm below it, in the shadow, is left to the shadow rules."""
    rng = np.random.default_rng(4)
    bone = np.c_[rng.uniform(-30, 30, (20_000, 2)), rng.normal(0, 0.4, 20_000)]
    above = np.c_[rng.uniform(-10, 10, (400, 2)), np.full(400, 6.0)]
    below = above - [0.0, 0.0, 12.0]
    cloud = np.r_[bone, above, below]
    view = np.tile([0.0, 0.0, -1.0], (len(cloud), 1))
    planes = fit_local_planes(cloud, 4.0, view=view)
    drop = false_echoes(cloud, planes, view, depth=30.0, ratio=2.0)
    assert drop[:20_000].mean() < 0.01
    assert drop[20_000:20_400].mean() > 0.95
    assert not drop[20_400:].any()


def hollow_beside_a_shaft(seed=6):
    """A shaft (convex, the larger part) and beside it a trough seen from inside (a hollow of the
    bone, concave toward the probe above), a fainter sheet 6 mm over the trough's floor, toward the
    probe; every point imaged looking down −z. Returns the cloud, the sheet's rows and the beams."""
    rng = np.random.default_rng(seed)
    bone, _ = shaft(n=20_000)
    a = np.radians(rng.uniform(-60, 60, 6_000))
    trough = np.c_[rng.uniform(-40, 40, 6_000), 80 + 15 * np.sin(a), 20 - 15 * np.cos(a)]
    trough[:, 2] += rng.normal(0.0, 0.4, len(trough))
    sheet = np.c_[rng.uniform(-15, 15, 400), rng.uniform(76, 84, 400), np.full(400, 11.0)]
    cloud = np.r_[bone, trough, sheet]
    return cloud, np.arange(len(bone) + len(trough), len(cloud)), np.tile([0.0, 0.0, -1.0], (len(cloud), 1))


def test_the_beams_a_clouds_order_tells_give_the_front_in_a_hollow():
    """The convexity rule looks into a hollow's floor and keeps the sheet over it; the beams find
    it in front. Beams listed from the far end are turned; beams lying along the surface (another
    order) are not beams, and convexity decides."""
    cloud, sheet, beams = hollow_beside_a_shaft()
    bone = np.setdiff1d(np.arange(len(cloud)), sheet)
    planes = fit_local_planes(cloud, 4.0)
    rule = dict(depth=30.0, ratio=2.0)
    convex = false_echoes(cloud, planes, None, **rule)
    assert convex[sheet].mean() < 0.5
    for told in (beams, -beams):
        drop = false_echoes(cloud, planes, None, beams=told, **rule)
        assert drop[sheet].mean() > 0.95 and drop[bone].mean() < 0.01
    along = np.tile([1.0, 0.0, 0.0], (len(cloud), 1))  # the shaft's axis: along every plane here
    assert np.array_equal(false_echoes(cloud, planes, None, beams=along, **rule), convex)
    unknown = false_echoes(cloud, planes, None, beams=np.zeros_like(cloud), **rule)
    assert np.array_equal(unknown, convex)


def test_small_components_are_the_groups_smaller_than_a_share_of_the_largest():
    rng = np.random.default_rng(5)
    big = rng.uniform(0, 50, (5_000, 3)) * [1, 1, 0]
    small = rng.normal(0, 0.5, (40, 3)) + [100, 0, 0]
    medium = rng.normal(0, 1.0, (400, 3)) + [0, 100, 0]
    pts = np.r_[big, small, medium]
    out = small_components(pts, 4.0, 0.02)
    assert out[5_000:5_040].all() and not out[:5_000].any() and not out[5_040:].any()
    assert not small_components(pts, 4.0, 0.0).any()
    # a group holding a spared point (a steep face's echo) stays whole
    spare = np.zeros(len(pts), dtype=bool)
    spare[5_010] = True
    assert not small_components(pts, 4.0, 0.02, spare).any()


def test_a_detached_group_in_the_plane_of_the_surface_is_kept_and_one_off_it_dropped():
    """Bone seen apart from the rest (past a gap in the coverage, its band of echoes as thick as
    the rest's) continues the surface in its plane; a cluster floating in the soft tissue beside it
    lies off that plane, and one frame's curve in that plane is no piece of surface."""
    rng = np.random.default_rng(6)
    bone = np.c_[rng.uniform(0, 50, (8_000, 2)), rng.normal(0, 0.8, 8_000)]
    patch = np.c_[rng.uniform(58, 66, 80), rng.uniform(10, 20, 80), rng.normal(0, 0.8, 80)]
    floating = patch + [0.0, 20.0, 15.0]
    x = rng.uniform(58, 70, 60)
    curve = np.c_[x, np.full(60, 40.0), 0.02 * (x - 58) ** 2]  # in the plane y = 40
    pts = np.r_[bone, patch, floating, curve]
    planes = fit_local_planes(pts, 4.0)
    out = small_components(pts, 4.0, 0.02, normals=planes.normal)
    assert not out[:8_080].any() and out[8_080:].all()
    # judged by size alone, the detached groups are all dropped
    assert small_components(pts, 4.0, 0.02)[8_000:].all()
