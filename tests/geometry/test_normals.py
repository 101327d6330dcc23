"""Normals (geometry/normals.py) and the sweep-based Poisson orientation (§7.2 alternative B): probe
positions carried from a sweep or the Python API through voxelisation and normalisation to the
method, the orientation choice, and its record in the sidecar."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

import ultraboneudf
from ultraboneudf import pipeline
from ultraboneudf.cli import main
from ultraboneudf.io import sidecar_path
from ultraboneudf.errors import InputError
from ultraboneudf.geometry.normals import orient_tangent_plane, orient_toward, pca_normals
from ultraboneudf.geometry.voxel import voxel_downsample, voxel_downsample_with
from ultraboneudf.methods import poisson
from ultraboneudf.methods.base import Fitted, Method
from ultraboneudf.methods.poisson import estimate_normals, resolve_orientation
from ultraboneudf.sweep import Sweep, write_sweep
from ultraboneudf.sweep.transforms import rigid_from_euler

RADIUS, STANDOFF = 20.0, 30.0


def two_band_sweep(n: int = 700, seed: int = 0):
    """Two slice bands of a bone shaft (cylinder of radius 20 mm along y), 7 mm apart along y.

    Band 0 (y 0–15 mm, θ 30°–150°) is imaged from above (probe plane z = +30), band 1 (y 22–37 mm,
    θ 200°–320°) from below (z = −30), as when a sweep goes round the limb. A linear probe's point
    lies straight down its scan line, so the probe position is the point moved to the probe plane.
    Returns points, true outward normals, probe positions (all (2n, 3), mm) and the band of each point.
    """
    rng = np.random.default_rng(seed)
    parts = []
    for band, (y0, t0, t1, z_probe) in enumerate([(0.0, 30, 150, STANDOFF), (22.0, 200, 320, -STANDOFF)]):
        theta = np.radians(rng.uniform(t0, t1, n))
        normal = np.c_[np.cos(theta), np.zeros(n), np.sin(theta)]
        p = RADIUS * normal + np.c_[np.zeros(n), rng.uniform(y0, y0 + 15.0, n), np.zeros(n)]
        probe = np.c_[p[:, 0], p[:, 1], np.full(n, z_probe)]
        parts.append((p, normal, probe, np.full(n, band)))
    return tuple(np.concatenate(arrays) for arrays in zip(*parts))


def facing(normals: np.ndarray, points: np.ndarray, probe: np.ndarray) -> np.ndarray:
    return (normals * (probe - points)).sum(axis=1) > 0


def test_probe_orientation_is_consistent_across_a_slice_gap():
    p, n_true, probe, band = two_band_sweep()
    raw = pca_normals(p, p, radius=np.inf, max_nn=30)
    assert (np.abs((raw * n_true).sum(axis=1)) > 0.95).all()
    toward = orient_toward(p, raw, probe)
    assert facing(toward, p, probe).all()  # 100 %
    assert ((toward * n_true).sum(axis=1) > 0).all()
    assert np.array_equal(estimate_normals(p, p, "knn30", viewpoints=probe), toward)
    # tangent-plane propagation cannot cross the gap: each band starts from its highest point turned
    # to +z, right for band 0, wrong for band 1 (seen from below), which flips as a whole
    tangent = orient_tangent_plane(p, raw, 15)
    outward = (tangent * n_true).sum(axis=1) > 0
    assert outward[band == 0].all() and not outward[band == 1].any()
    assert np.array_equal(estimate_normals(p, p, "knn30"), tangent)


def test_probe_positions_follow_the_voxel_means():
    pts = np.array([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0], [1.0, 1.0, 1.0]])
    probe = np.array([[0.0, 0.0, 10.0], [0.0, 0.0, 20.0], [5.0, 5.0, 5.0]])
    v, a = voxel_downsample_with(pts, probe, 0.1)
    np.testing.assert_array_equal(v, voxel_downsample(pts, 0.1))
    np.testing.assert_allclose(a, [[0.0, 0.0, 15.0], [5.0, 5.0, 5.0]])
    p, _, pr, _ = two_band_sweep()
    perm = np.random.default_rng(1).permutation(len(p))
    v1, a1 = voxel_downsample_with(p, pr, 2.0)
    v2, a2 = voxel_downsample_with(p[perm], pr[perm], 2.0)
    np.testing.assert_allclose(v1, v2)
    np.testing.assert_allclose(a1, a2)
    v0, a0 = voxel_downsample_with(p, pr, 0.0)
    assert np.array_equal(v0, p) and np.array_equal(a0, pr) and a0 is not pr
    with pytest.raises(ValueError, match="attributes"):
        voxel_downsample_with(p, pr[:-1], 0.1)


def test_reconstruct_hands_normalised_voxel_probe_positions_to_the_method(monkeypatch):
    seen = {}

    def with_probe(points, cfg, device, seed, progress, *, probe=None):
        seen.update(points=points, probe=probe)
        return Fitted(info={"poisson_orientation": "probe"})

    def without_probe(points, cfg, device, seed, progress):
        seen.update(points=points, probe="never passed")
        return Fitted()

    p, _, probe, _ = two_band_sweep()
    monkeypatch.setattr(pipeline, "get_method", lambda name: Method(with_probe, takes_probe=True))
    rec = ultraboneudf.reconstruct(p, preset="fast", device="cpu", probe_positions=probe, **{"data.voxel_size_mm": 2.0})
    v, a = voxel_downsample_with(p, probe, 2.0)
    assert len(v) < len(p)
    np.testing.assert_allclose(seen["points"], rec.normalizer.forward(v))
    np.testing.assert_allclose(seen["probe"], rec.normalizer.forward(a))
    assert rec.mesh is None and rec.sidecar()["method_info"] == {"poisson_orientation": "probe"}
    ultraboneudf.reconstruct(p, preset="fast", device="cpu")
    assert seen["probe"] is None
    with pytest.raises(InputError, match="one row per point"):
        ultraboneudf.reconstruct(p, preset="fast", device="cpu", probe_positions=probe[:-1])
    bad = probe.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        ultraboneudf.reconstruct(p, preset="fast", device="cpu", probe_positions=bad)
    # a method that has no use for probe positions never receives them
    monkeypatch.setattr(pipeline, "get_method", lambda name: Method(without_probe))
    ultraboneudf.reconstruct(p, preset="fast", device="cpu", probe_positions=probe)
    assert seen["probe"] == "never passed"


@pytest.fixture
def stub_solver(monkeypatch):
    """Poisson without a Poisson library: record what the solver would get, return a small mesh."""
    calls = []

    def solve(points, normals, depth=9, scale=1.1, backend="auto", threads=0):
        calls.append((points, normals))
        return trimesh.creation.icosahedron()

    monkeypatch.setattr(poisson, "resolve_backend", lambda name: "stub")
    monkeypatch.setattr(poisson, "screened_poisson", solve)
    return calls


@pytest.mark.parametrize("choice,with_probe,expected", [
    ("auto", True, "probe"), ("auto", False, "tangent"), ("probe", True, "probe"), ("tangent", True, "tangent")])
def test_poisson_orientation_choice_and_sidecar(stub_solver, choice, with_probe, expected):
    p, n_true, probe, band = two_band_sweep()
    rec = ultraboneudf.reconstruct(p, device="cpu", method="poisson", probe_positions=probe if with_probe else None,
                                   **{"poisson.orientation": choice, "data.voxel_size_mm": 0.0})
    assert rec.sidecar()["method_info"]["poisson_orientation"] == expected
    assert rec.sidecar()["config"]["poisson"]["orientation"] == choice
    surface, normals = stub_solver[-1]
    _, row = cKDTree(rec.normalizer.forward(p)).query(surface)
    outward = (normals * n_true[row]).sum(axis=1) > 0
    if expected == "probe":
        assert outward.all()
    else:
        assert outward[band[row] == 0].all() and not outward[band[row] == 1].any()


def test_poisson_orientation_errors():
    p, _, probe, _ = two_band_sweep(n=100)
    with pytest.raises(InputError, match=r"unknown poisson.orientation 'sideways'; choose one of auto, tangent, probe"):
        ultraboneudf.reconstruct(p, device="cpu", method="poisson", probe_positions=probe,
                                 **{"poisson.orientation": "sideways"})
    with pytest.raises(InputError, match="needs per-point probe positions"):
        ultraboneudf.reconstruct(p, device="cpu", method="poisson", **{"poisson.orientation": "probe"})
    assert resolve_orientation("auto", True) == "probe" and resolve_orientation("auto", False) == "tangent"


def test_cli_reconstruct_sweep_orients_toward_the_probe(stub_solver, tmp_path):
    # frames 1 mm apart along z; image x → world x, the beam (image y) → world +y; a flat bone 5 mm deep
    poses = np.stack([rigid_from_euler([0, 0, float(i)], [0, 0, 0]) for i in range(30)])
    masks = np.zeros((30, 20, 40), dtype=bool)
    masks[:, 10, 5:35] = True
    sweep = Sweep(image_to_world=poses, spacing_mm=0.5, image_size=(40, 20), masks=masks, pixel_offset=0.5)
    write_sweep(sweep, tmp_path / "sw", write_images=False)
    out = tmp_path / "mesh.ply"
    # the stub solver's mesh (a unit icosahedron) is nowhere near the data: no support trim
    assert main(["reconstruct", str(tmp_path / "sw"), "-o", str(out), "--method", "poisson", "--quiet",
                 "--set", "extract.trim_mm=0", "--set", "extract.trim_normal_mm=0",
                 "--set", "extract.trim_rim_mm=0"]) == 0
    side = json.loads(sidecar_path(out).read_text())
    assert side["method_info"]["poisson_orientation"] == "probe"
    _, normals = stub_solver[-1]
    assert (normals[:, 1] < -0.99).all()  # back up the beam, toward the probe at y = 0


def test_poisson_run_with_probe_orientation():
    pytest.importorskip("pymeshlab")
    p, _, probe, _ = two_band_sweep()
    rec = ultraboneudf.reconstruct(p, device="cpu", method="poisson", probe_positions=probe,
                                   **{"poisson.octree_depth": 6, "poisson.solver_threads": 1})
    assert rec.mesh is not None and len(rec.mesh.faces) > 100
    assert rec.sidecar()["method_info"] == {"poisson_orientation": "probe", "poisson_backend": "pymeshlab"}
    d, _ = cKDTree(p).query(rec.mesh.vertices)
    assert (d < 3.0).mean() > 0.1  # the closed surface wraps the two bands
