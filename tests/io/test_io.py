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


@pytest.mark.parametrize("name, header", [("s.csv", ""), ("s.csv", "id;x;y;z\n"), ("s.xyz", ""), ("s.txt", "")])
@pytest.mark.parametrize("decimal", [".", ","])
def test_semicolon_separated_text_with_either_decimal_mark(tmp_path, name, header, decimal):
    # as spreadsheets write a table where the comma is the decimal mark
    pts = _cloud()
    lead = "7;" if header else ""
    rows = (lead + ";".join(f"{v:.6f}".replace(".", decimal) for v in row) for row in pts)
    path = tmp_path / name
    path.write_text(header + "\n".join(rows) + "\n")
    np.testing.assert_allclose(load_points(path), pts, atol=1e-6)


def test_a_pts_file_opens_with_its_point_count(tmp_path):
    pts = _cloud()
    path = tmp_path / "scan.pts"   # Leica PTS: the count, then x y z intensity r g b
    path.write_text(f"{len(pts)}\n" + "\n".join(f"{a:.6f} {b:.6f} {c:.6f} -1200 255 255 255" for a, b, c in pts))
    np.testing.assert_allclose(load_points(path), pts, atol=1e-6)


@pytest.mark.parametrize("header", ["", '"x","y","z"\n'])
def test_quoted_csv_fields(tmp_path, header):
    pts = _cloud()
    path = tmp_path / "q.csv"
    path.write_text(header + "\n".join(f'"{a:.6f}","{b:.6f}","{c:.6f}"' for a, b, c in pts))
    np.testing.assert_allclose(load_points(path), pts, atol=1e-6)


def test_an_archive_of_one_array_holds_the_points_whatever_its_name(tmp_path):
    pts = _cloud()
    np.savez(tmp_path / "one.npz", pts)
    np.testing.assert_allclose(load_points(tmp_path / "one.npz"), pts)
    np.savez(tmp_path / "two.npz", a=pts, b=pts)
    with pytest.raises(InputError, match=r"two\.npz: no array named 'points' \(it holds a, b\)"):
        load_points(tmp_path / "two.npz")


def test_points_one_per_column_are_refused_with_the_fix():
    with pytest.raises(InputError, match=r"shape \(3, 200\), one point per column.*transpose"):
        validate_points(_cloud().T)


def test_a_decimal_comma_line_among_semicolons_is_named(tmp_path):
    lines = [";".join(f"{v:.6f}".replace(".", ",") for v in row) for row in _cloud()]
    lines[40] = "1,5;zwei;3,0"
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"bad\.csv: line 41: cannot parse numbers"):
        load_points(path)


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


def _ply_header(n, fmt="ascii 1.0"):
    return (f"ply\nformat {fmt}\nelement vertex {n}\nproperty float x\nproperty float y\n"
            f"property float z\nend_header\n")


def test_a_ply_that_ends_before_its_declared_vertices_is_refused(tmp_path):
    pts = np.random.default_rng(0).random((100, 3)) * 50
    ascii_ply = tmp_path / "short.ply"
    ascii_ply.write_text(_ply_header(1000) + "\n".join(" ".join(map(str, p)) for p in pts) + "\n")
    with pytest.raises(InputError, match=r"short.ply: the header declares 1,000 vertices but the file holds 100"):
        load_points(ascii_ply)
    binary = tmp_path / "short_bin.ply"
    binary.write_bytes(_ply_header(1000, "binary_little_endian 1.0").encode() + pts.astype("<f4").tobytes())
    with pytest.raises(InputError, match=r"declares 1,000 vertices \(12,000 bytes\) but the file holds 1,200 bytes"):
        load_points(binary)


def test_a_ply_header_declaring_a_billion_vertices_is_refused_before_reading(tmp_path):
    bomb = tmp_path / "bomb.ply"
    bomb.write_bytes(_ply_header(10**9, "binary_little_endian 1.0").encode() + b"\0" * 1200)
    with pytest.raises(InputError, match="declares 1,000,000,000 vertices, more than the limit"):
        load_points(bomb)
    not_ply = tmp_path / "fake.ply"
    not_ply.write_text("solid nothing\n")
    with pytest.raises(InputError, match="fake.ply: not a PLY file"):
        load_points(not_ply)


def test_coordinates_beyond_a_kilometre_are_refused_before_the_numerics():
    pts = np.random.default_rng(0).random((500, 3)) * 50
    pts[3] = 1e30
    with pytest.raises(InputError, match=r"scan.xyz: 1 point\(s\) have a coordinate beyond ±10⁶ mm"):
        validate_points(pts, source="scan.xyz")


def test_an_os_error_while_reading_is_one_line(tmp_path, monkeypatch):
    """A failing disk (EIO) while reading: the reader's OSError is raised here (the permission case
    runs for real in io/test_outputs.py)."""
    from ultraboneudf import io as uio

    path = tmp_path / "locked.xyz"
    np.savetxt(path, _cloud())

    def failing(p):
        raise OSError(5, "Input/output error", str(p))

    monkeypatch.setitem(uio.POINT_READERS, ".xyz", failing)
    with pytest.raises(InputError, match=r"locked.xyz: cannot read the file \(Input/output error\)"):
        load_points(path)


@pytest.mark.parametrize("suffix", [".ply", ".npz"])
def test_a_cloud_written_from_a_sweep_gives_back_its_probe_positions_and_frames(tmp_path, suffix):
    from ultraboneudf.io import encode_points, load_sweep_columns
    from ultraboneudf.sweep.compound import CompoundedPoints

    rng = np.random.default_rng(0)
    n = 500
    cp = CompoundedPoints(points=rng.uniform(0, 40, (n, 3)), frame_index=np.repeat(np.arange(5), 100),
                          probe_position=rng.uniform(0, 40, (n, 3)),
                          beam_direction=np.tile([0.0, 0.0, -1.0], (n, 1)), pixel=rng.uniform(0, 100, (n, 2)))
    path = tmp_path / f"cloud{suffix}"
    path.write_bytes(encode_points(path, cp))
    points = load_points(path)
    probe, frames = load_sweep_columns(path, len(points))
    np.testing.assert_array_equal(points, cp.points)
    np.testing.assert_array_equal(probe, cp.probe_position)
    np.testing.assert_array_equal(frames, cp.frame_index)


def test_clouds_without_sweep_columns_give_none_and_bad_columns_name_the_file(tmp_path):
    from ultraboneudf.io import load_sweep_columns

    pts = np.random.default_rng(1).uniform(0, 40, (200, 3))
    trimesh.PointCloud(pts).export(tmp_path / "plain.ply")
    np.savez(tmp_path / "plain.npz", points=pts)
    np.savetxt(tmp_path / "plain.xyz", pts)
    np.savez(tmp_path / "frames_only.npz", points=pts, frame_index=np.zeros(200, dtype=int))
    for name in ("plain.ply", "plain.npz", "plain.xyz", "frames_only.npz"):
        assert load_sweep_columns(tmp_path / name, 200) == (None, None)
    np.savez(tmp_path / "short.npz", points=pts, probe_position=pts[:-1])
    with pytest.raises(InputError, match=r"short.npz: the probe positions must be one row of three per "
                                         r"point \(200\), got shape \(199, 3\)"):
        load_sweep_columns(tmp_path / "short.npz", 200)


def test_a_cloud_larger_than_memory_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """Text is read as a stream and its size estimated from its first lines; a ``.npy`` or ``.npz``
    from its header: a cloud whose points cannot fit is refused, naming the memory it needs."""
    from ultraboneudf.io import inputs

    pts = _cloud(5000)
    text = tmp_path / "c.xyz"
    np.savetxt(text, pts)
    big = tmp_path / "big.npy"
    with open(big, "wb") as fh:          # a header declaring 10⁹ points and no data
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (10**9, 3)})
    with pytest.raises(InputError, match=r"big.npy: its 1,000,000,000 points need about 67.1 GiB of memory"):
        load_points(big)
    np.testing.assert_allclose(load_points(text), pts, atol=1e-6)
    monkeypatch.setattr(inputs, "available_memory", lambda: 100_000)
    with pytest.raises(InputError, match=r"c.xyz: its 5,\d\d\d lines of text need about"):
        load_points(text)
    np.savez(tmp_path / "c.npz", points=pts)
    with pytest.raises(InputError, match="c.npz: its 5,000 points need"):
        load_points(tmp_path / "c.npz")


def test_a_long_text_cloud_is_read_whole_and_a_late_bad_line_is_named(tmp_path):
    """Past the first MiB read to size it, the stream still reads every line, and names a bad one."""
    pts = _cloud(60_000)
    lines = [f"{a:.9f} {b:.9f} {c:.9f}" for a, b, c in pts]
    path = tmp_path / "long.xyz"
    path.write_text("# scanner export\n" + "\n".join(lines) + "\n")
    assert path.stat().st_size > 2 << 20
    np.testing.assert_allclose(load_points(path), pts, atol=1e-8)
    lines[50_000] = "1.0 2.0 three"
    path.write_text("# scanner export\n" + "\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"long.xyz: line 50002: cannot parse"):
        load_points(path)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # trimesh's normals of the damaged mesh written here
def test_meshes_are_refused_when_damaged_and_read_as_given_otherwise(tmp_path):
    """A NaN vertex, a face naming a vertex the file lacks, a header promising more faces than the
    file holds: one line naming the file. A sound mesh with no triangles is ``None`` (a counted
    failure of a method), never an error."""
    from ultraboneudf.io import load_mesh, read_mesh

    m = trimesh.creation.icosphere(subdivisions=2)
    v = m.vertices.copy()
    v[7] = [np.inf, 0, 0]
    trimesh.Trimesh(v, m.faces, process=False).export(tmp_path / "inf.stl")
    with pytest.raises(InputError, match=r"inf.stl: \d+ vertices are NaN or infinite"):
        read_mesh(tmp_path / "inf.stl")
    lines = trimesh.exchange.ply.export_ply(m, encoding="ascii").decode().splitlines()
    (tmp_path / "cut.ply").write_text("\n".join(lines[:-10]) + "\n")
    with pytest.raises(InputError, match="cut.ply: the header declares 320 faces but the file holds 310"):
        read_mesh(tmp_path / "cut.ply")
    binary = trimesh.exchange.ply.export_ply(m)
    (tmp_path / "cut_b.ply").write_bytes(binary[:-100])
    with pytest.raises(InputError, match="cut_b.ply"):
        read_mesh(tmp_path / "cut_b.ply")
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                                        "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
                                        "end_header\n")
    assert read_mesh(tmp_path / "empty.ply") is None
    with pytest.raises(InputError, match="holds no triangles"):
        load_mesh(tmp_path / "empty.ply")
    m.export(tmp_path / "ok.obj")
    assert np.array_equal(read_mesh(tmp_path / "ok.obj").faces, m.faces)
