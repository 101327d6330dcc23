"""A short CPU run of every method through ``reconstruct`` (same input handling, normalisation and
sidecar as the core method), with tiny networks and a few hundred iterations at most."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

import ultraboneudf
from ultraboneudf.errors import InputError
from ultraboneudf.methods.poisson import resolve_backend, screened_poisson

RADIUS, LENGTH = 20.0, 40.0
# five hidden layers so that the skip into layer 4 (CAP-UDF, FUNSR) exists
TINY = {"train.iters": 100, "train.batch": 300, "train.warmup": 10, "model.hidden": (32, 32, 32, 32, 32),
        "data.grid_queries": 500, "grid.resolution": 32, "extract.max_depth": 6}
PARAMS = {"no_skip": 5 * 32 + 4 * 32 * 34 + 34, "skip4": 5 * 32 + 3 * 32 * 34 + 29 * 34 + 34}
HAS_POISSON = any(importlib.util.find_spec(m) is not None for m in ("pymeshlab", "open3d"))


def patch_points(n: int = 800, seed: int = 0) -> np.ndarray:
    """A half-cylinder sheet in mm: open and curved, like a bone surface seen from one side."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, np.pi, n)
    return np.c_[RADIUS * np.cos(theta), rng.uniform(0, LENGTH, n), RADIUS * np.sin(theta)]


def run(method: str, **extra):
    return ultraboneudf.reconstruct(patch_points(), preset="official", device="cpu", seed=1, method=method,
                                    **{**TINY, **extra})


def near_input_fraction(rec, tol_mm: float) -> float:
    from scipy.spatial import cKDTree
    d, _ = cKDTree(patch_points()).query(rec.mesh.vertices)
    return float((d < tol_mm).mean())


@pytest.mark.parametrize("method,term", [("carotidudf", "pull"), ("vanilla_udf", "pull"),
                                         ("ultraboneudf_pull", "pull"), ("funsr", "pull")])
def test_short_run_pull_family(method, term):
    # FUNSR's 132k-parameter discriminator makes its iterations ~3× dearer on a CPU
    rec = run(method, **({"train.iters": 40} if method == "funsr" else {"train.iters": 60}))
    assert rec.mesh is not None and len(rec.mesh.faces) > 50
    hist = rec.history[term]
    assert hist[-1] < hist[0]
    side = rec.sidecar()
    assert side["method"] == method and side["config"]["loss"]["lambda_gs"] == 0.0
    assert side["counts"]["parameters"] == PARAMS["skip4" if method == "funsr" else "no_skip"]
    assert "extract_s" in side["timings"]
    if side["config"]["extract"]["mode"] == "udf2sdf":
        # §5.4: the conversion in use is recorded; its sign flips add sheets far from the data
        assert side["config"]["grid"]["udf2sdf"] == "normal-sign"
        assert near_input_fraction(rec, 10.0) > 0.1
    else:
        assert near_input_fraction(rec, 10.0) > 0.3


def test_short_run_capudf_expands_once():
    rec = run("capudf", **{"train.iters": 80, "capudf.expand_at": 50, "capudf.expand_batch": 600, "capudf.expand_candidates": 3000,
                           "capudf.total_queries": 8_000, "grid.cell_threshold": 0.02})
    assert rec.counts["surface_points"] % 60 == 0
    assert rec.counts["expanded_points"] > 0
    assert rec.history["cd"][-1] < rec.history["cd"][0]
    assert rec.mesh is not None and len(rec.mesh.vertices) == 3 * len(rec.mesh.faces)  # triangle soup
    # the grid box is the data's bounding box + 0.05 unit per side: the mesh cannot leave it
    lo, hi = patch_points().min(axis=0), patch_points().max(axis=0)
    margin = 0.05 * (hi - lo).max() + 1e-6
    assert (rec.mesh.vertices >= lo - margin).all() and (rec.mesh.vertices <= hi + margin).all()


def test_funsr_field_is_signed():
    rec = run("funsr", **{"train.iters": 20})
    assert rec.counts["discriminator_parameters"] == 132_353
    assert set(rec.history) >= {"pull", "scc", "disc", "adl", "total"}
    assert rec.mesh.is_winding_consistent


@pytest.mark.skipif(not HAS_POISSON, reason="no screened-Poisson library (pip install 'ultraboneudf[poisson]')")
def test_poisson_on_a_sphere_and_on_the_sheet():
    d = np.random.default_rng(0).normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # one thread: the OpenMP solver crawls when the (shared) CPU is oversubscribed
    mesh = screened_poisson(0.3 * d, d, depth=6, threads=1)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3).max() < 0.02
    rec = run("poisson", **{"poisson.octree_depth": 6, "poisson.solver_threads": 1})
    assert rec.mesh is not None and rec.counts["parameters"] == 0
    # Poisson closes the open sheet (§7.4): the mesh wraps it, so it reaches the input
    assert near_input_fraction(rec, 3.0) > 0.2
    # a method that gives a mesh directly: fit + extract is that mesh, trimmed as reconstruct trims it
    surface = ultraboneudf.fit(patch_points(), preset="official", device="cpu", seed=1, method="poisson",
                               **{**TINY, "poisson.octree_depth": 6, "poisson.solver_threads": 1})
    assert surface.field is None
    np.testing.assert_array_equal(surface.extract().faces, rec.mesh.faces)
    assert len(surface.extract(trim_mm=3.0).faces) < len(rec.mesh.faces)   # the closed body's far side


def test_poisson_backend_errors_are_actionable():
    with pytest.raises(InputError, match="poisson.backend"):
        resolve_backend("nope")
    missing = [m for m in ("pymeshlab", "open3d") if importlib.util.find_spec(m) is None]
    for name in missing:
        with pytest.raises(InputError, match="pip install"):
            resolve_backend(name)
    if not HAS_POISSON:
        with pytest.raises(InputError, match=r"ultraboneudf\[poisson\]"):
            run("poisson")


@pytest.mark.parametrize("method", ["carotidudf", "funsr", "capudf", "ultraboneudf_pull"])
def test_every_method_runs_under_the_default_preset(method):
    """The default ``robust`` preset's pre-processing (local planes, outliers, denoising) and its
    ``surface`` distance target reach every method that samples queries as UltraBoneUDF does."""
    rec = ultraboneudf.reconstruct(patch_points(3000), device="cpu", seed=1, method=method,
                                   **{**TINY, "train.iters": 30})
    assert rec.preset == "robust" and rec.config.loss.distance_target == "surface"
    assert rec.counts["input_points"] == 3000 and "surface_fit_s" in rec.timings
