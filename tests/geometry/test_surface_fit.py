"""Robust local planes and the data surface between points, on planes, slices and spheres."""

import numpy as np
import pytest

from ultraboneudf.geometry.data_surface import DataSurface
from ultraboneudf.geometry.surface_fit import fit_local_planes, radius_for_density, steep_echoes


def noisy_plane(n=20_000, noise=0.5, seed=0, half=30.0):
    """Points of z = 0 over [−half, half]² (mm) with Gaussian noise of ``noise`` mm along z."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-half, half, (n, 2))
    return np.c_[xy, rng.normal(0.0, noise, n)]


def slices(spacing=1.5, step=0.15, noise=0.0, half=20.0, seed=0):
    """Lines y = const on z = 0 every ``spacing`` mm (a sweep's slices), points every ``step`` mm,
    noise along z."""
    rng = np.random.default_rng(seed)
    xs = np.arange(-half, half, step)
    pts = np.concatenate([np.c_[xs, np.full_like(xs, y), np.zeros_like(xs)]
                          for y in np.arange(-half, half + 1e-9, spacing)])
    pts[:, 2] += rng.normal(0.0, noise, len(pts)) if noise else 0.0
    return pts


@pytest.mark.parametrize("per_mm2, expected", [(5.0, 4.0), (1.0 / np.pi, 6.0), (0.03, 8.0)])
def test_the_planes_radius_widens_on_a_sparse_surface_by_the_root_of_the_shortfall(per_mm2, expected):
    """36 points wanted within 4 mm: a dense plane keeps 4 mm; one of 1/π points per mm² (16 within
    4 mm) gets 4 × √(36/16) = 6 mm; a very sparse one stops at twice the radius."""
    half = 60.0
    pts = noisy_plane(n=int(per_mm2 * (2 * half) ** 2), noise=0.1, seed=2, half=half)
    got = radius_for_density(pts, 4.0, 36)
    assert got == pytest.approx(expected, rel=0.06)
    assert radius_for_density(pts, 4.0, 0) == 4.0


def test_planes_of_a_noisy_plane_give_its_normal_noise_and_the_denoised_points():
    pts = noisy_plane()
    pl = fit_local_planes(pts, 4.0)
    inner = np.abs(pts[:, :2]).max(axis=1) < 25
    assert pl.valid[inner].all()
    assert np.percentile(np.abs(pl.normal[inner, 2]), 1) > 0.99 and np.abs(pl.normal[inner, 2]).min() > 0.97
    # the spread is the noise (σ = 0.5 mm; a point's distance from a plane it helped fit is ~10%
    # smaller), the projection removes most of it
    assert np.median(pl.spread[inner]) == pytest.approx(0.5, rel=0.15)
    assert np.abs(pl.projected(pts)[inner, 2]).mean() < 0.25 * np.abs(pts[inner, 2]).mean()
    assert np.all(pl.radius[inner] == 4.0)
    assert pl.outliers(3.0)[inner].mean() < 0.01


def test_false_echoes_below_the_surface_are_removed_or_moved_onto_it():
    """False echoes 1.5–10 mm under a surface imaged from above: the plane test flags most of those
    within the fit radius and the sparse deep scatter; projection moves others onto the surface; the
    shadow test (points beneath another point along their beam) removes what is left."""
    from ultraboneudf.geometry.surface_fit import shadowed

    pts = noisy_plane(n=40_000, noise=0.3)
    rng = np.random.default_rng(1)
    near = np.c_[rng.uniform(-20, 20, (150, 2)), -rng.uniform(1.5, 3.5, 150)]
    deep = np.c_[rng.uniform(-20, 20, (100, 2)), -rng.uniform(5.0, 10.0, 100)]
    cloud = np.r_[pts, near, deep]
    n = len(pts)
    pl = fit_local_planes(cloud, 4.0)
    out = pl.outliers(3.0, 0.4)
    assert out[n:n + 150].mean() > 0.5 and out[n + 150:].mean() > 0.9
    assert out[:n].mean() < 0.01                 # the surface itself
    # the robust fit is not pulled toward them
    assert np.abs(pl.offset[:n][np.abs(pts[:, :2]).max(axis=1) < 15]).mean() < 0.4
    kept = pl.projected(cloud)[~out]
    down = np.tile([0.0, 0.0, -1.0], (len(kept), 1))
    clean = kept[~shadowed(kept, down, 1.5)]
    inner = np.abs(clean[:, :2]).max(axis=1) < 25
    assert np.abs(clean[inner, 2]).max() < 1.5   # no echo left under the surface
    assert len(clean) > 0.98 * n


def test_a_lone_slice_has_no_plane_unless_a_wider_radius_reaches_the_next():
    # one noisy line: its best plane would be the image plane (normal along y), refused when the
    # view direction (down the beam, −z) is known; slices 6 mm apart need the 8 mm radius
    line = slices(spacing=100.0, noise=0.8, half=20.0)
    down = np.tile([0.0, 0.0, -1.0], (len(line), 1))
    assert not fit_local_planes(line, 4.0, view=down).valid.any()
    sparse = slices(spacing=6.0, noise=0.3)
    pl = fit_local_planes(sparse, 4.0, view=np.tile([0.0, 0.0, -1.0], (len(sparse), 1)))
    inner = np.abs(sparse[:, :2]).max(axis=1) < 10
    assert pl.valid[inner].mean() > 0.95 and np.all(pl.radius[inner][pl.valid[inner]] >= 8.0)
    assert np.abs(pl.normal[inner][pl.valid[inner], 2]).min() > 0.95
    # a clean line with no view: collinear, no plane
    assert not fit_local_planes(slices(spacing=100.0), 4.0).valid.any()


def tilted(angle_deg, **kw):
    """:func:`noisy_plane` turned about y by ``angle_deg``: its normal is that far from −z."""
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return noisy_plane(**kw) @ rot.T, rot @ [0.0, 0.0, 1.0]


@pytest.mark.parametrize("angle", [65.0, 75.0])
def test_a_steep_face_gets_an_orientation_but_is_neither_moved_nor_judged(angle):
    pts, true_normal = tilted(angle, n=8_000, noise=0.3, half=15.0)
    down = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    inner = np.abs(pts[:, 1]) < 10.0
    refused = fit_local_planes(pts, 4.0, view=down)            # beyond the 60° the planes accept
    assert not refused.valid.any() and not refused.steep.any() and not refused.gap.any()
    pl = fit_local_planes(pts, 4.0, view=down, steep_deg=80.0)
    assert pl.steep[inner].all() and not pl.valid.any()
    assert np.abs(pl.normal[inner] @ true_normal).min() > 0.98
    assert np.all(pl.gap[inner] == 4.0)
    assert not pl.offset.any() and not pl.spread.any()
    np.testing.assert_array_equal(pl.projected(pts), pts)
    assert not pl.outliers(3.0)[inner].any()                   # only isolation could drop them
    kept = pl.subset(inner).scaled(0.5)
    assert kept.steep.all() and np.all(kept.gap == 2.0)
    # steeper than the limit: nothing; within 60°: an ordinary plane, never a steep one
    assert not fit_local_planes(tilted(86.0, n=8_000, noise=0.05, half=15.0)[0], 4.0, view=down,
                                steep_deg=80.0).radius.any()
    facing = fit_local_planes(tilted(40.0, n=8_000, noise=0.3, half=15.0)[0], 4.0, view=down,
                              steep_deg=80.0)
    assert facing.valid[inner].all() and not facing.steep.any()


def test_the_few_echoes_of_a_steep_face_are_spared_and_a_deep_scatter_is_not():
    """A face 70° from the beam with an echo every 3.8 mm (five points within 4 mm, a surface needs
    six: sparse) beside a dense surface facing the probe, with echoes scattered 5–10 mm under it:
    the 8 mm radius gives the face a steep plane, so its echoes are spared; the scatter still goes."""
    dense = noisy_plane(n=40_000, noise=0.3)
    rng = np.random.default_rng(2)
    deep = np.c_[rng.uniform(-20, 20, (100, 2)), -rng.uniform(5.0, 10.0, 100)]
    a = np.radians(70.0)
    u, v = np.meshgrid(np.arange(-15.2, 15.3, 3.8), np.arange(-15.2, 15.3, 3.8))
    face = np.c_[u.ravel() * np.cos(a), v.ravel(), u.ravel() * np.sin(a)] + [60.0, 0.0, 0.0]
    face += rng.normal(0.0, 0.1, face.shape)
    cloud = np.r_[dense, deep, face]
    down = np.tile([0.0, 0.0, -1.0], (len(cloud), 1))
    on_face = np.arange(len(cloud)) >= len(dense) + len(deep)
    inner = on_face & (np.abs(cloud[:, 1]) < 10.0) & (np.abs(cloud[:, 0] - 60.0) < 4.0)
    pl = fit_local_planes(cloud, 4.0, view=down, steep_deg=80.0)
    assert pl.sparse[on_face].all() and pl.steep[inner].all() and np.all(pl.radius[inner] == 8.0)
    spare = steep_echoes(cloud, down, pl, 3.0)
    assert spare[inner].all() and not spare[:len(dense) + len(deep)].any()
    out = pl.outliers(3.0, 0.4, spare)
    assert not out[inner].any()
    assert out[len(dense):len(dense) + len(deep)].mean() > 0.9 and out[:len(dense)].mean() < 0.01
    # not spared, the face is a sparse scatter like the other
    assert pl.outliers(3.0, 0.4)[on_face].all()


def test_false_echoes_that_line_up_into_steep_planes_under_a_bone_are_not_spared():
    """Slices every 1.5 mm over a cylinder of radius 20 mm seen from above, 0.8 mm noise, 3% false
    echoes up to 10 mm under it: a few of the deep ones line up with each other into planes
    60–80° from the beam at 8 or 16 mm, but the bone lies above them on their beam."""
    rng = np.random.default_rng(0)
    pts = []
    for y in np.arange(0.75, 40.0, 1.5):
        x = np.arange(-14.1, 14.1, 0.15)
        z = np.sqrt(400.0 - x * x) + rng.normal(0.0, 0.8, len(x))
        echo = rng.random(len(x)) < 0.03
        z[echo] -= rng.uniform(0.0, 10.0, echo.sum())
        pts.append(np.c_[x, np.full_like(x, y), z])
    pts = np.concatenate(pts)
    down = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    pl = fit_local_planes(pts, 4.0, view=down, steep_deg=80.0)
    deep = np.hypot(pts[:, 0], pts[:, 2]) < 17.0
    lone = pl.sparse & pl.steep & (pl.radius > pl.base)
    assert (lone & deep).sum() >= 3
    assert not (steep_echoes(pts, down, pl, 3.0) & deep).any()


def test_data_surface_bridges_gaps_between_slices_but_not_past_the_rim():
    pts = slices(spacing=5.0, step=0.2, half=10.0)           # lines y = −10, −5, 0, 5, 10
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    surface = DataSurface(pts, up, bridge=np.full(len(pts), 6.0))
    q = np.array([[0.0, 2.5, 0.3],    # midway between two slices, 0.3 mm above: 0.3
                  [0.0, 1.0, 0.5],    # near one slice: the plane, not the 1 mm to the line
                  [0.0, 0.5, -0.2],
                  [0.0, 12.0, 0.3],   # 2 mm past the last slice: the distance to it
                  [25.0, 0.0, 0.0]])   # beyond the lines' ends (x ≤ 9.8): to the last point
    np.testing.assert_allclose(surface.distance(q), [0.3, 0.5, 0.2, np.hypot(2.0, 0.3), 15.2],
                               atol=1e-9)
    # gaps longer than the bridge stay open; a rim reach extends past the last points
    narrow = DataSurface(pts, up, bridge=np.full(len(pts), 2.0))
    assert narrow.distance(q[:1])[0] == pytest.approx(np.hypot(2.5, 0.3))
    reach = DataSurface(pts, up, bridge=np.zeros(len(pts)), reach=1.5)
    assert reach.distance(q[3:4])[0] == pytest.approx(np.hypot(0.5, 0.3))
    # without planes it is the distance to the nearest point
    bare = DataSurface(pts, np.zeros_like(pts), bridge=np.full(len(pts), 6.0), reach=3.0)
    assert bare.distance(q[:1])[0] == pytest.approx(np.hypot(2.5, 0.3))
    # along the normal: the same over a gap, the height above the plane past the rim, 0 without planes
    total, normal, _ = surface.distances(q)
    np.testing.assert_allclose(total, surface.distance(q))
    np.testing.assert_allclose(normal, [0.3, 0.5, 0.2, 0.3, 0.0], atol=1e-9)
    assert bare.distances(q[3:4])[1][0] == 0.0


def test_data_surface_follows_two_tilted_planes_across_a_gap():
    # points on a sphere of radius 30 in two caps separated by a 3 mm band; across the band the
    # interpolated plane distance stays within the sagitta of the 4 mm fits ((4/2)²/(2·30) ≈ 0.07 mm)
    # plus that of the 1.5 mm half-gap (0.04 mm)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(40_000, 3))
    v = 30.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    cap = (v[:, 2] > 20) & (np.abs(v[:, 0]) > 1.5)           # a 3 mm gap across x = 0
    pts = v[cap]
    pl = fit_local_planes(pts, 4.0)
    surface = DataSurface(pts, pl.normal, bridge=4.0 * np.ones(len(pts)))
    on = np.array([[0.0, y, np.sqrt(900 - y * y)] for y in np.linspace(-10, 10, 21)])
    assert surface.distance(on).max() < 0.15


def test_data_surface_spans_a_missing_run_on_a_curved_bone_by_the_chord():
    """Slices every 1.5 mm over a cylinder of radius 10 mm (a talus-sized curvature), three missing
    (a 6 mm gap), planes fitted at 4 mm as the pipeline does: the rims' planes differ by about 35°,
    so the gap is spanned by the chord, and on the true surface across it the distance stays below
    0.5 mm: the chord's sagitta, 3² / (2·10) = 0.45 mm, and the fitted normals' error. The rims'
    planes extrapolated into the gap miss it by 0.87 mm: a rim's fit sees its neighbours on one
    side only."""
    r = 10.0
    xs = np.arange(-7.5, 7.6, 1.5)
    xs = xs[np.abs(xs) > 2.0]
    ys = np.arange(-10.0, 10.0, 0.15)
    pts = np.concatenate([np.c_[np.full_like(ys, x), ys, np.full_like(ys, np.sqrt(r * r - x * x))]
                          for x in xs])
    pl = fit_local_planes(pts, 4.0)
    surface = DataSurface(pts, pl.normal, bridge=1.0 * pl.gap, reach=0.5 * pl.gap)
    on = np.array([[x, y, np.sqrt(r * r - x * x)] for x in np.linspace(-3.0, 3.0, 13)
                   for y in np.linspace(-5.0, 5.0, 5)])
    assert surface.distance(on).max() < 0.5


def test_denoising_follows_the_curvature_of_a_small_bone():
    """Points of a sphere of radius 10 mm (a talus-sized curvature) with 0.15 mm noise: moved onto
    their local quadrics they keep the radius (a plane at the 4 mm radius would shrink it by about
    (4/2)²/(2·10) = 0.2 mm) and lose most of the noise."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(60_000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > 0.3]
    pts = v * (10.0 + rng.normal(0.0, 0.15, (len(v), 1)))
    err = np.linalg.norm(fit_local_planes(pts, 4.0).projected(pts), axis=1) - 10.0
    inner = v[:, 2] > 0.5
    assert abs(err[inner].mean()) < 0.03
    assert np.abs(err[inner]).mean() < 0.3 * np.abs(np.linalg.norm(pts[inner], axis=1) - 10.0).mean()
