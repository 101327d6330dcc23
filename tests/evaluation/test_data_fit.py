"""The data-fit self-check (``extraction.data_fit``): a mesh against the points it was built from."""

import numpy as np
import pytest
import trimesh

from ultraboneudf.evaluation.data_fit import data_fit


def disc_mesh(radius: float, n: int = 96) -> trimesh.Trimesh:
    """The disc of ``radius`` in the plane z = 0, a fan of 48 rings × n sectors (area within 0.1%)."""
    rings = np.linspace(0, radius, 49)[1:]
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    v = np.vstack([[0.0, 0.0, 0.0]] + [np.c_[r * np.cos(t), r * np.sin(t), np.zeros(n)] for r in rings])
    ring = lambda k: 1 + k * n + np.arange(n)  # noqa: E731
    f = [np.c_[np.zeros(n, int), ring(0), np.roll(ring(0), -1)]]
    for k in range(len(rings) - 1):
        a, b = ring(k), ring(k + 1)
        f += [np.c_[a, b, np.roll(b, -1)], np.c_[a, np.roll(b, -1), np.roll(a, -1)]]
    return trimesh.Trimesh(v, np.vstack(f), process=False)


def disc_points(radius: float, count: int = 40_000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    r, t = radius * np.sqrt(rng.uniform(0, 1, count)), rng.uniform(0, 2 * np.pi, count)
    return np.c_[r * np.cos(t), r * np.sin(t), np.zeros(count)]


def test_a_mesh_on_its_own_points_fits():
    fit = data_fit(disc_mesh(10.0), disc_points(10.0), 1.0)
    assert fit["threshold_mm"] == 1.0
    assert fit["input_far_fraction"] == 0.0 and fit["mesh_far_area_fraction"] == 0.0
    assert fit["input_p95_mm"] < 0.1  # the samples are ≈ threshold/10 apart


def test_input_the_mesh_does_not_reach():
    """Points on a disc of radius 10, mesh of radius 5, threshold 1: the points beyond radius 6 are
    far, an area fraction (100 − 36)/100 = 0.64; the mesh itself is all supported."""
    fit = data_fit(disc_mesh(5.0), disc_points(10.0), 1.0)
    assert fit["input_far_fraction"] == pytest.approx(0.64, abs=0.01)
    assert fit["mesh_far_area_fraction"] == 0.0
    assert fit["input_p95_mm"] == pytest.approx(10 * np.sqrt(0.95) - 5, abs=0.1)


def test_mesh_area_the_points_do_not_support():
    """Mesh of radius 10 over points of radius 5, threshold 1: faces whose mean vertex distance is
    ≥ 1 lie beyond radius ≈ 6, an area fraction ≈ 0.64 (ring width 0.21 sets the tolerance)."""
    fit = data_fit(disc_mesh(10.0), disc_points(5.0), 1.0)
    assert fit["mesh_far_area_fraction"] == pytest.approx(0.64, abs=0.03)
    assert fit["input_far_fraction"] == 0.0


def test_no_mesh_covers_nothing():
    fit = data_fit(None, disc_points(1.0, 200), 1.0)
    assert fit["input_far_fraction"] == 1.0 and fit["mesh_far_area_fraction"] == 0.0


def test_many_points_are_subsampled_deterministically():
    pts = disc_points(10.0, 450_000)
    a, b = data_fit(disc_mesh(5.0), pts, 1.0), data_fit(disc_mesh(5.0), pts, 1.0)
    assert a == b and a["input_far_fraction"] == pytest.approx(0.64, abs=0.01)
