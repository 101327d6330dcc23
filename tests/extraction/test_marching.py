"""Grid extractors of the baselines (extraction/marching.py) on analytic fields: the generated
marching-cubes table, SDF marching cubes (FUNSR), CAP-UDF pseudo-sign per-cell marching cubes and
CarotidUDF's UDF→SDF conversions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ultraboneudf.config import ExtractConfig, GridConfig
from ultraboneudf.errors import InputError
from ultraboneudf.extraction import extract_mesh
from ultraboneudf.extraction.marching import (EDGES, TRIANGLES, capudf_marching_cubes, marching_cubes_volume,
                                              sdf_marching_cubes, udf_to_sdf_marching_cubes)
from ultraboneudf.fields.analytic import PlaneUDF, SphereUDF

RES = 48
STEP = 2.0 / (RES - 1)


def test_table_uses_only_sign_change_edges_and_at_most_five_triangles():
    assert TRIANGLES.shape == (256, 5, 3)
    assert (TRIANGLES[0] < 0).all() and (TRIANGLES[255] < 0).all()
    for case in range(1, 255):
        neg = [(case >> k) & 1 for k in range(8)]
        used = TRIANGLES[case][TRIANGLES[case] >= 0]
        assert len(used) > 0
        assert all(neg[EDGES[e, 0]] != neg[EDGES[e, 1]] for e in used)


def test_volume_marching_cubes_of_random_field_is_closed_where_interior():
    # a random field whose border is positive: the welded mesh must be closed and consistently wound
    rng = np.random.default_rng(0)
    vol = rng.normal(size=(12, 12, 12))
    vol[[0, -1], :, :] = vol[:, [0, -1], :] = vol[:, :, [0, -1]] = 1.0
    v, f = marching_cubes_volume(vol)
    import trimesh
    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent


def test_sdf_marching_cubes_on_sphere_is_closed_outward_and_accurate():
    mesh = sdf_marching_cubes(SphereUDF(radius=0.3, signed=True), resolution=RES)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 0.3).max() < 0.05 * STEP
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * 0.3**3, rel=0.02)  # > 0: normals outward


def test_sdf_marching_cubes_on_plane_is_exact_and_faces_positive_side():
    mesh = sdf_marching_cubes(PlaneUDF(offset=0.013, signed=True), resolution=RES)
    assert np.abs(mesh.vertices[:, 2] - 0.013).max() < 1e-12  # linear field: interpolation is exact
    assert mesh.area == pytest.approx(4.0)
    assert (mesh.face_normals[:, 2] > 0.999).all()


def test_sdf_marching_cubes_without_surface_returns_none():
    assert sdf_marching_cubes(PlaneUDF(offset=5.0, signed=True), resolution=16) is None


def test_capudf_per_cell_marching_cubes_on_sphere_udf():
    lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    mesh = capudf_marching_cubes(SphereUDF(radius=0.3), lo, hi, resolution=RES, threshold=0.02)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 0.3).max() < 0.05 * (1.0 / (RES - 1))
    assert mesh.area == pytest.approx(4 * np.pi * 0.09, rel=0.02)
    # a triangle soup: no vertex is shared between faces
    assert len(mesh.vertices) == 3 * len(mesh.faces)


def test_capudf_per_cell_marching_cubes_on_plane_udf_and_anisotropic_box():
    lo, hi = np.array([-0.5, -0.3, -0.2]), np.array([0.5, 0.3, 0.2])
    mesh = capudf_marching_cubes(PlaneUDF(offset=0.013), lo, hi, resolution=RES, threshold=0.02)
    assert np.abs(mesh.vertices[:, 2] - 0.013).max() < 1e-12
    assert mesh.area == pytest.approx(1.0 * 0.6)


def test_capudf_cell_threshold_filters_cells():
    lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    # every cell touching the plane has min u ≤ half a step; a threshold below that keeps fewer cells
    full = capudf_marching_cubes(PlaneUDF(offset=0.013), lo, hi, resolution=RES, threshold=0.05)
    tight = capudf_marching_cubes(PlaneUDF(offset=0.013), lo, hi, resolution=RES, threshold=1e-4)
    assert tight is None or len(tight.faces) < len(full.faces)


def _sphere_points(n: int = 4000, r: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    d = np.random.default_rng(1).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return r * d, d


def test_udf2sdf_normal_sign_closes_a_sphere_with_orientation_from_the_normals():
    p, n = _sphere_points()
    out = udf_to_sdf_marching_cubes(SphereUDF(radius=0.3), "normal-sign", RES, surface=p, normals=n)
    assert out.is_watertight
    assert np.abs(np.linalg.norm(out.vertices, axis=1) - 0.3).max() < 0.05 * STEP
    assert out.volume > 0
    flipped = udf_to_sdf_marching_cubes(SphereUDF(radius=0.3), "normal-sign", RES, surface=p, normals=-n)
    assert flipped.volume == pytest.approx(-out.volume)


def test_udf2sdf_normal_sign_needs_normals():
    with pytest.raises(InputError, match="normal-sign"):
        udf_to_sdf_marching_cubes(SphereUDF(radius=0.3), "normal-sign", 16)


def test_udf2sdf_eps_shell_gives_two_layers_and_projection_collapses_them():
    shell = udf_to_sdf_marching_cubes(PlaneUDF(offset=0.013), "eps-shell", RES)
    z = shell.vertices[:, 2]
    assert np.allclose(np.abs(z - 0.013), STEP, atol=1e-9)
    assert (z > 0.013).any() and (z < 0.013).any()
    projected = udf_to_sdf_marching_cubes(PlaneUDF(offset=0.013), "eps-shell", RES, project=True)
    assert np.abs(projected.vertices[:, 2] - 0.013).max() < 1e-9


def test_udf2sdf_local_flip_is_capudf_on_the_cube():
    a = udf_to_sdf_marching_cubes(SphereUDF(radius=0.3), "local-flip", 32, threshold=0.03)
    b = capudf_marching_cubes(SphereUDF(radius=0.3), np.full(3, -1.0), np.full(3, 1.0), 32, 0.03)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


@pytest.mark.parametrize("mode", ["capudf_mc", "sdf_mc", "udf2sdf"])
def test_extract_mesh_dispatches_grid_modes(mode):
    grid = GridConfig(resolution=32, udf2sdf="eps-shell", cell_threshold=0.05)
    p, n = _sphere_points(500)
    if mode == "capudf_mc":
        grid.box = "surface"
    field = SphereUDF(radius=0.3, signed=(mode == "sdf_mc"))
    mesh = extract_mesh(field, ExtractConfig(mode=mode), surface=p, normals=n, grid=grid)
    assert mesh is not None and len(mesh.faces) > 100
    r = np.linalg.norm(mesh.vertices, axis=1)
    tol = 2.0 / 31 * (1.1 if mode == "udf2sdf" else 0.1)  # eps-shell sits one step off the surface
    assert np.abs(r - 0.3).max() < tol


def test_extract_mesh_far_trimming_and_surface_box_need_surface():
    cfg = ExtractConfig(mode="capudf_mc")
    grid = GridConfig(resolution=32, box="surface", cell_threshold=0.05)
    with pytest.raises(InputError, match="surface"):
        extract_mesh(SphereUDF(radius=0.3), cfg, grid=grid)
    p, _ = _sphere_points(500)
    cap = p[p[:, 2] > 0.1]  # only the top cap is data: far trimming removes the rest
    grid.box, grid.far = "domain", 0.02
    mesh = extract_mesh(SphereUDF(radius=0.3), cfg, surface=cap, grid=grid)
    assert mesh.vertices[:, 2].min() > 0.1 - 0.03


def test_field_gradients_only_where_needed_device_agnostic():
    # the extractor evaluates through the Field interface: float32 fields work the same way
    field = SphereUDF(radius=0.3, dtype=torch.float32)
    mesh = capudf_marching_cubes(field, np.full(3, -0.5), np.full(3, 0.5), resolution=32, threshold=0.03)
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3).max() < 1e-3
