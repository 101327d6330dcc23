import numpy as np
import pytest
import torch

from ultraboneudf.config import preset
from ultraboneudf.geometry import Normalizer, farthest_point_sampling, knn_distance, voxel_downsample
from ultraboneudf.geometry.queries import anchors, grid_queries, surface_subset
from ultraboneudf.methods.ultraboneudf import prepare


def test_normalizer_round_trip_and_unit_box():
    pts = np.random.default_rng(0).uniform([-5, 10, 100], [15, 20, 104], (1000, 3))
    n = Normalizer.fit(pts)
    u = n.forward(pts)
    assert np.isclose(np.ptp(u, axis=0).max(), 1.0)
    np.testing.assert_allclose((u.max(0) + u.min(0)) / 2, 0.0, atol=1e-12)
    np.testing.assert_allclose(n.inverse(u), pts, atol=1e-12)


def test_voxel_mean_is_deterministic_and_sorted():
    pts = np.array([[0.0, 0, 0], [0.04, 0, 0], [0.5, 0, 0], [0.0, 0.5, 0], [0.52, 0.01, 0]])
    out = voxel_downsample(pts, 0.1)
    np.testing.assert_allclose(out, [[0.02, 0, 0], [0, 0.5, 0], [0.51, 0.005, 0]])
    perm = np.random.default_rng(1).permutation(len(pts))
    np.testing.assert_allclose(voxel_downsample(pts[perm], 0.1), out)


def test_fps_greedy_order_and_prefix_property():
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [10, 0, 0], [5, 0, 0], [2, 0, 0]])
    np.testing.assert_array_equal(farthest_point_sampling(pts, 4), [0, 2, 3, 4])
    cloud = np.random.default_rng(2).random((3000, 3))
    big = farthest_point_sampling(cloud, 300)
    np.testing.assert_array_equal(farthest_point_sampling(cloud, 100), big[:100])


@pytest.mark.parametrize("leaf", [7, 64, 512])
def test_bucketed_fps_is_the_plain_greedy_result(leaf):
    """Pruning by blocks changes no choice: same indices, ties (duplicates, a coarse z grid) to
    the lowest index, a start other than 0, a block count that leaves padding."""
    from ultraboneudf.geometry.fps import _fps_bucketed, _fps_numpy

    rng = np.random.default_rng(5)
    cloud = rng.normal(size=(5_003, 3))
    cloud[:500] = cloud[500:1000]            # exact duplicates
    cloud[:, 2] = np.round(cloud[:, 2], 1)   # many equal coordinates
    np.testing.assert_array_equal(_fps_bucketed(cloud, 700, 0, leaf), _fps_numpy(cloud, 700, 0))
    np.testing.assert_array_equal(_fps_bucketed(cloud, 300, 4_321, leaf), _fps_numpy(cloud, 300, 4_321))
    patch = np.c_[rng.random((4_000, 2)), np.zeros(4_000)]   # a flat surface: every z equal
    np.testing.assert_array_equal(_fps_bucketed(patch, 400, 0, leaf), _fps_numpy(patch, 400, 0))
    assert np.array_equal(_fps_bucketed(cloud[:10], 10, 0, leaf), _fps_numpy(cloud[:10], 10, 0))


def test_official_subset_rule():
    cloud = np.random.default_rng(3).random((60_001, 3))
    P = surface_subset(cloud, "official", 60_000, (5_000, 15_000), 40_000)
    assert P.shape == (20_000, 3)
    assert len(np.unique(P, axis=0)) == 15_000
    np.testing.assert_array_equal(P[:5_000], P[5_000:10_000])
    small = cloud[:60_000]
    assert surface_subset(small, "official", 60_000, (5_000, 15_000), 40_000) is small


def test_sigma_counts_duplicates_at_zero():
    pts = np.random.default_rng(4).random((500, 3))
    doubled = np.concatenate([pts, pts])
    assert np.all(knn_distance(doubled, 1) == 0.0)
    assert np.all(knn_distance(pts, 1) > 0.0)


def test_grid_queries_come_from_both_lattices():
    q = grid_queries(30_000, np.random.default_rng(0))
    assert q.shape == (30_000, 3) and len(np.unique(q, axis=0)) == 30_000
    assert q.min() >= -1.0 and q.max() <= 1.0 and (np.abs(q) > 0.5).any()


def test_anchor_targets_and_filter():
    surface = np.array([[0.0, 0.0, 0.0]] * 2)
    pts, tgt = anchors(surface, "official", 10, squared=True, min_target=0.1)
    np.testing.assert_allclose(tgt, (pts**2).sum(1))
    assert np.all(tgt > 0.1) and len(pts) < 1000
    pts, tgt = anchors(np.random.default_rng(0).random((50, 3)) - 0.5, "bbox", 10, False, -1.0)
    assert len(pts) == 1000 and np.all(tgt >= 0)


def test_official_query_count_for_20000_rows():
    cloud = np.random.default_rng(5).random((60_500, 3)) - 0.5
    data = prepare(cloud, preset("official"), device="cpu", seed=0)
    assert data.surface.shape == (20_000, 3)
    assert data.queries.shape == (430_000, 3)       # 400,000 Gaussian + 30,000 grid
    assert 0 < len(data.anchors) <= 1000
    # queries of row i are rows 20i … 20i+19, offsets N(0, σ(p_i)² I): |offset|/σ is chi(3)-distributed
    sigma = torch.as_tensor(knn_distance(data.surface.double().numpy(), 50), dtype=torch.float32)
    d = (data.queries[:400_000].reshape(20_000, 20, 3) - data.surface[:, None]).norm(dim=2) / sigma[:, None]
    assert abs(float(d.median()) - 1.538) < 0.02


def test_the_nearest_neighbour_back_ends_agree():
    """The KD-tree, the tensors' index and the chunked brute force find the same nearest points (no
    ties among random points), and every KD-tree of the package is made in geometry/neighbors.py."""
    from pathlib import Path

    import ultraboneudf
    from ultraboneudf.geometry.neighbors import NearestIndex, brute_force_nearest, kd_tree

    rng = np.random.default_rng(0)
    points, queries = rng.normal(size=(3000, 3)), rng.normal(size=(1000, 3)) * 1.5
    _, expected = kd_tree(points).query(queries)
    p, q = torch.as_tensor(points), torch.as_tensor(queries)
    assert np.array_equal(NearestIndex(p).query(q).numpy(), expected)
    assert np.array_equal(brute_force_nearest(q, p, chunk=333).numpy(), expected)
    package = Path(ultraboneudf.__file__).parent
    builders = sorted(str(f.relative_to(package)) for f in package.rglob("*.py") if "cKDTree" in f.read_text())
    assert builders == ["geometry/neighbors.py"]


def test_unit_rows_scales_each_vector_and_keeps_unknown_ones_zero():
    from ultraboneudf.geometry.vectors import unit_rows

    v = np.array([[3.0, 0.0, 4.0], [0.0, 0.0, 0.0], [0.0, -2e-20, 0.0]])
    u = unit_rows(v)
    np.testing.assert_allclose(u, [[0.6, 0.0, 0.8], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert not np.isnan(u).any()
    np.testing.assert_array_equal(v[0], [3.0, 0.0, 4.0])  # the input is left as it was
    stacked = unit_rows(np.stack([v, 2 * v]))  # any leading shape: the last axis is the vector
    np.testing.assert_allclose(stacked, np.stack([u, u]))
