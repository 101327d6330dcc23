"""Metrics of docs/ALGORITHMS.md §6.2 on analytic geometry whose answers are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ultraboneudf.errors import InputError
from ultraboneudf.evaluation import (
    JSON_KEYS,
    SHARE_KEYS,
    DegenerateMeshError,
    chamfer_hd95,
    evaluate,
    metrics_from_distances,
    prepare_ground_truth,
    pseudo_gt_mask,
    sample_surface,
)
from ultraboneudf.geometry.neighbors import grid_distances, nearest_distances

N = 100_000  # samples per surface in these tests (5e6 is for the benchmark)


def square(size: float = 10.0, z: float = 0.0, n: int = 1) -> trimesh.Trimesh:
    """An axis-aligned square [0, size]² at height z, split into 2·n² triangles."""
    g = np.linspace(0.0, size, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    i = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    return trimesh.Trimesh(v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]), process=False)


def sphere(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=6, radius=radius)


# ---------------------------------------------------------------------------------------------
# sampling


def test_sampling_is_seeded_and_on_the_surface():
    m = sphere(3.0)
    a = sample_surface(m, 20_000, seed=7)
    b = sample_surface(m, 20_000, seed=7)
    c = sample_surface(m, 20_000, seed=8)
    assert a.shape == (20_000, 3) and a.dtype == np.float64
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    r = np.linalg.norm(a, axis=1)
    assert r.max() <= 3.0 + 1e-9 and r.min() > 3.0 * 0.999  # on the (inscribed) facets


def test_sampling_is_uniform_by_area_and_ignores_zero_area_faces():
    # a soup: a 1×1 triangle, a 2×2 triangle (4× the area), a zero-area face, a duplicated vertex
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],
                  [5, 0, 0], [7, 0, 0], [5, 2, 0],
                  [9, 0, 0], [10, 0, 0], [11, 0, 0]], dtype=float)
    f = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [6, 6, 6]])
    pts = sample_surface((v, f), 200_000, seed=1)
    small = (pts[:, 0] <= 1.0).sum()
    big = ((pts[:, 0] >= 5.0) & (pts[:, 0] <= 7.0)).sum()
    assert (pts[:, 0] > 8.0).sum() == 0  # zero-area faces get no sample
    assert big / small == pytest.approx(4.0, rel=0.03)
    # uniform inside a face: the mean is the centroid
    assert pts[pts[:, 0] <= 1.0, :2].mean(axis=0) == pytest.approx([1 / 3, 1 / 3], abs=0.01)


def test_sampling_handles_non_manifold_soups_and_nan_vertices():
    # three triangles sharing one edge (non-manifold), plus a face touching a NaN vertex
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [np.nan, 0, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4], [0, 1, 5]])
    pts = sample_surface((v, f), 10_000, seed=0)
    assert np.isfinite(pts).all()


@pytest.mark.parametrize("mesh", [
    (np.zeros((0, 3)), np.zeros((0, 3), dtype=int)),
    (np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]), np.array([[0, 1, 2]])),  # collinear: zero area
])
def test_degenerate_meshes_raise_a_clear_error(mesh):
    with pytest.raises(DegenerateMeshError):
        sample_surface(mesh, 10)


def test_bad_face_indices_are_an_input_error():
    with pytest.raises(InputError, match="refers to vertex 7"):
        sample_surface((np.zeros((3, 3)), np.array([[0, 1, 7]])), 10)


# ---------------------------------------------------------------------------------------------
# metrics on analytic shapes


def test_identical_samplings_give_zero():
    s = sample_surface(sphere(1.0), N, seed=0)
    m = chamfer_hd95(s, s)
    assert m["cd_mm"] == 0.0 and m["hd95_mm"] == 0.0


def test_same_mesh_gives_cd_near_zero():
    r = evaluate(sphere(1.0), sphere(1.0), samples=N, seed=0)
    spacing = np.sqrt(4 * np.pi / N)  # mean sample spacing on the unit sphere
    assert not r.failed
    assert r.cd_mm < 0.5 * spacing
    assert r.hd95_mm < 1.5 * spacing


def test_concentric_spheres_radius_1_and_2():
    r = evaluate(sphere(1.0), sphere(2.0), samples=30_000, seed=0)
    assert r.cd_mm == pytest.approx(1.0, abs=0.01)
    assert r.hd95_mm == pytest.approx(1.0, abs=0.02)
    assert r.d_rg_mean_mm == pytest.approx(1.0, abs=0.01)
    assert r.d_gr_mean_mm == pytest.approx(1.0, abs=0.01)
    assert r.hd95_union_mm == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("h", [0.25, 1.0])
def test_plane_and_its_shifted_copy(h):
    r = evaluate(square(10.0, 0.0, 4), square(10.0, h, 4), samples=N, seed=3)
    assert r.cd_mm == pytest.approx(h, abs=0.01)
    assert r.hd95_mm == pytest.approx(h, abs=0.02)


def test_hd95_on_a_constructed_distribution():
    d_rg = np.arange(101, dtype=float)  # 0 … 100: linear P95 = 95.0
    d_gr = np.linspace(0.0, 10.0, 11)   # P95 = 9.5
    m = metrics_from_distances(d_rg, d_gr)
    assert m["hd95_rg_mm"] == pytest.approx(95.0)
    assert m["hd95_gr_mm"] == pytest.approx(9.5)
    assert m["hd95_mm"] == pytest.approx(95.0)  # max of the directed P95
    assert m["hd95_mean_mm"] == pytest.approx(52.25)
    pooled = np.sort(np.concatenate([d_rg, d_gr]))  # 112 values: P95 at rank 0.95·111 = 105.45
    assert m["hd95_union_mm"] == pytest.approx(pooled[105] + 0.45 * (pooled[106] - pooled[105]))
    assert m["cd_mm"] == pytest.approx(0.5 * (50.0 + 5.0))
    # P95 interpolates linearly between order statistics
    assert metrics_from_distances(np.array([0.0, 1.0]), np.array([0.0]))["hd95_rg_mm"] == pytest.approx(0.95)


def test_pseudo_gt_filter_keeps_a_known_count():
    # 1000 points on a line x = 0..999 mm; the raw cloud is a single point at the origin:
    # exactly the points with x ≤ τ survive (boundary inclusive)
    gt = np.stack([np.arange(1000.0), np.zeros(1000), np.zeros(1000)], axis=1)
    raw = np.zeros((1, 3))
    assert pseudo_gt_mask(gt, raw, 2.0).sum() == 3   # x = 0, 1, 2
    assert pseudo_gt_mask(gt, raw, 1.0).sum() == 2   # x = 0, 1
    assert pseudo_gt_mask(gt, raw, 0.5).sum() == 1


def test_pseudo_gt_restricts_the_ground_truth_to_the_scanned_part():
    # ground truth: a 10×10 square; raw cloud: its left half (x < 5) on a 0.25 mm lattice
    g = np.arange(0.0, 5.0, 0.25)
    raw = np.stack(np.meshgrid(g, np.arange(0.0, 10.01, 0.25), indexing="ij"), -1).reshape(-1, 2)
    raw = np.c_[raw, np.zeros(len(raw))]
    truth = prepare_ground_truth(square(10.0, 0.0, 4), raw, pseudo_gt_mm=1.0, samples=N, seed=0)
    frac = len(truth.points) / N
    assert truth.pseudo_gt_mm == 1.0
    assert frac == pytest.approx((4.75 + 1.0) / 10.0, abs=0.01)  # x ≤ 4.75 + τ
    # a reconstruction of only the scanned half has a small CD against the pseudo GT
    half = trimesh.Trimesh(square(10.0, 0.0, 4).vertices * [0.575, 1, 1], square(10.0, 0.0, 4).faces)
    r = evaluate(half, truth)
    assert r.cd_mm < 0.05 and r.pseudo_gt_mm == 1.0 and r.samples_gt == len(truth.points)
    # the default τ with raw points is the paper's 2 mm, and it is recorded
    assert evaluate(half, square(10.0, 0.0, 4), raw_points=raw, samples=10_000).pseudo_gt_mm == 2.0


def test_pseudo_gt_errors_are_input_errors():
    with pytest.raises(InputError, match="without the raw"):
        prepare_ground_truth(square(), None, pseudo_gt_mm=1.0, samples=100)
    with pytest.raises(InputError, match="no ground-truth sample"):
        prepare_ground_truth(square(), np.full((5, 3), 1000.0), samples=1000)


def test_no_mesh_is_a_counted_failure_not_zero():
    for recon in (None, (np.zeros((0, 3)), np.zeros((0, 3), dtype=int)),
                  (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]))):
        r = evaluate(recon, square(), samples=1000)
        assert r.failed and r.reason
        assert r.cd_mm is None and r.hd95_mm is None
        js = r.to_json()
        assert list(js) == list(JSON_KEYS)
        assert js["cd_mm"] is None and js["samples"] == 1000


def test_json_keys_are_exactly_those_of_the_design():
    js = evaluate(square(), square(z=0.5), samples=5000).to_json()
    assert list(js) == ["cd_mm", "hd95_mm", "d_rg_mean_mm", "d_gr_mean_mm", "hd95_rg_mm", "hd95_gr_mm",
                        "samples", "pseudo_gt_mm"]
    assert js["samples"] == 5000 and js["pseudo_gt_mm"] is None
    assert all(isinstance(js[k], float) for k in JSON_KEYS[:6])


def test_shares_within_a_distance_on_analytic_geometry():
    gt = square(10.0, 0.0, 4)
    # the square and an equal one 5 mm above it: half the area on the ground truth, all of it covered
    two = trimesh.util.concatenate([square(10.0, 0.0, 4), square(10.0, 5.0, 4)])
    r = evaluate(two, gt, samples=N, within_mm=1.0)
    assert r.on_gt == pytest.approx(0.5, abs=0.01) and r.covered == 1.0
    # the left half of the square: all of it on the ground truth, which is covered up to x = 5 + 1 mm
    half = trimesh.Trimesh(gt.vertices * [0.5, 1, 1], gt.faces)
    r = evaluate(half, gt, samples=N, within_mm=1.0)
    assert r.on_gt == 1.0 and r.covered == pytest.approx(0.6, abs=0.01)
    # the square 0.5 mm above: everything within 1 mm, nothing within 0.4 mm
    for within, share in ((1.0, 1.0), (0.4, 0.0)):
        r = evaluate(square(10.0, 0.5, 4), gt, samples=20_000, within_mm=within)
        assert r.on_gt == share and r.covered == share and r.within_mm == within
    assert list(r.to_json()) == list(JSON_KEYS + SHARE_KEYS)
    assert evaluate(square(10.0, 0.5, 4), gt, samples=5000).on_gt is None  # not asked for
    with pytest.raises(InputError, match="share distance"):
        evaluate(square(), gt, samples=1000, within_mm=-1.0)


def test_share_on_the_ground_truth_measures_to_the_whole_of_it():
    # the raw cloud sees the left half (x ≤ 4.75), so the pseudo GT is x ≤ 5.75; the reconstruction is
    # the right half: all of it on the ground truth, which only the pseudo GT's strip x ≥ 4.5 is near
    gt = square(10.0, 0.0, 4)
    g = np.arange(0.0, 5.0, 0.25)
    raw = np.stack(np.meshgrid(g, np.arange(0.0, 10.01, 0.25), indexing="ij"), -1).reshape(-1, 2)
    raw = np.c_[raw, np.zeros(len(raw))]
    right = trimesh.Trimesh(gt.vertices * [0.5, 1, 1] + [5.0, 0, 0], gt.faces)
    r = evaluate(right, gt, raw_points=raw, pseudo_gt_mm=1.0, samples=N, within_mm=0.5)
    assert r.on_gt == 1.0 and r.covered == pytest.approx((5.75 - 4.5) / 5.75, abs=0.01)
    kept = prepare_ground_truth(gt, raw, pseudo_gt_mm=1.0, samples=N, keep_whole=True)
    again = evaluate(right, kept, within_mm=0.5)
    assert (again.on_gt, again.covered, again.cd_mm) == (r.on_gt, r.covered, r.cd_mm)
    with pytest.raises(InputError, match="keep_whole"):
        evaluate(right, prepare_ground_truth(gt, raw, pseudo_gt_mm=1.0, samples=N), within_mm=0.5)
    failed = evaluate(None, kept, within_mm=0.5).to_json()
    assert failed["within_mm"] == 0.5 and failed["on_gt"] is None and failed["covered"] is None


def test_same_seed_same_numbers_and_prepared_ground_truth_reuse():
    a = evaluate(sphere(1.0), sphere(1.2), samples=20_000, seed=5)
    b = evaluate(sphere(1.0), sphere(1.2), samples=20_000, seed=5)
    truth = prepare_ground_truth(sphere(1.2), samples=20_000, seed=5)
    c = evaluate(sphere(1.0), truth)
    assert a.cd_mm == b.cd_mm == c.cd_mm and a.hd95_mm == c.hd95_mm


def test_grid_search_matches_the_kd_tree():
    rng = np.random.default_rng(0)
    ref = sample_surface(sphere(5.0), 20_000, seed=1)
    q = np.concatenate([sample_surface(sphere(5.3), 3000, seed=2), rng.normal(size=(50, 3)) * 20])
    expected = nearest_distances(q, ref)
    got = grid_distances(q, ref, device="cpu")
    assert np.allclose(got, expected, atol=1e-4)
