import numpy as np
import pytest
import trimesh

from ultraboneudf.errors import InputError
from ultraboneudf.io import load_points, save_json, save_mesh, validate_points


def _cloud(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-10, 10, (n, 2)), rng.normal(0, 0.1, n)]


@pytest.mark.parametrize("suffix", [".xyz", ".txt", ".csv", ".ply", ".npy", ".npz"])
def test_round_trip_every_format(tmp_path, suffix):
    pts = _cloud()
    path = tmp_path / f"cloud{suffix}"
    if suffix in (".xyz", ".txt"):
        np.savetxt(path, np.c_[pts, np.ones(len(pts))], fmt="%.9f")   # an extra column is ignored
    elif suffix == ".csv":
        path.write_text("intensity,x,y,z\n" + "\n".join(f"1,{a:.9f},{b:.9f},{c:.9f}" for a, b, c in pts))
    elif suffix == ".ply":
        trimesh.PointCloud(pts).export(path)
    elif suffix == ".npy":
        np.save(path, pts)
    else:
        np.savez(path, points=pts)
    np.testing.assert_allclose(load_points(path), pts, atol=1e-6)


def test_comma_separated_xyz(tmp_path):
    pts = _cloud()
    path = tmp_path / "c.xyz"
    path.write_text("\n".join(f"{a},{b},{c}" for a, b, c in pts))
    np.testing.assert_allclose(load_points(path), pts, atol=1e-9)


def test_missing_file_and_unknown_extension(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_points(tmp_path / "none.xyz")
    bad = tmp_path / "cloud.abc"
    bad.write_text("1 2 3\n")
    with pytest.raises(InputError, match="unknown point cloud extension"):
        load_points(bad)


def test_unparsable_line_is_named(tmp_path):
    lines = [f"{a} {b} {c}" for a, b, c in _cloud()]
    lines[57] = "1.0 oops 2.0"
    path = tmp_path / "bad.xyz"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"bad\.xyz: line 58"):
        load_points(path)


def test_nan_too_few_and_degenerate():
    pts = _cloud()
    pts[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN or Inf"):
        validate_points(pts)
    with pytest.raises(InputError, match="only 99 points"):
        validate_points(_cloud(99))
    with pytest.raises(InputError, match="identical"):
        validate_points(np.ones((500, 3)))
    t = np.linspace(0, 1, 500)[:, None]
    with pytest.raises(InputError, match="collinear"):
        validate_points(t * [1.0, 2.0, 3.0] + 5)
    plane = np.c_[_cloud()[:, :2], np.zeros(200)]
    assert validate_points(plane).shape == (200, 3)     # a flat patch is a valid open surface


def test_atomic_writes_leave_no_partial_file(tmp_path):
    mesh = trimesh.creation.icosphere()
    save_mesh(mesh, tmp_path / "m.ply")
    assert trimesh.load(tmp_path / "m.ply").faces.shape == mesh.faces.shape
    with pytest.raises(TypeError):
        save_json({"x": object()}, tmp_path / "s.json")
    assert not (tmp_path / "s.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]
    with pytest.raises(InputError, match="unknown mesh extension"):
        save_mesh(mesh, tmp_path / "m.vtk")
