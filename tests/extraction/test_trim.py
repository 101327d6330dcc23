"""The support trim (``extract.trim_mm``) on an analytic mesh: a plane larger than its data; the
grazing trim (``extract.trim_grazing_deg``) on a shelf with a wall hanging from its rim."""

import numpy as np
import pytest
import trimesh

from ultraboneudf.extraction import trim_to_support


def plane(n=81, half=1.0):
    """The square [−half, half]² at z = 0 as a triangle grid."""
    a = np.linspace(-half, half, n)
    xx, yy = np.meshgrid(a, a, indexing="ij")
    v = np.c_[xx.ravel(), yy.ravel(), np.zeros(n * n)]
    return trimesh.Trimesh(v, _grid_faces(n, n), process=False)


@pytest.fixture
def disc_support():
    """Points densely covering the disc of radius 0.5 in the plane z = 0."""
    rng = np.random.default_rng(0)
    r, t = 0.5 * np.sqrt(rng.uniform(0, 1, 20_000)), rng.uniform(0, 2 * np.pi, 20_000)
    return np.c_[r * np.cos(t), r * np.sin(t), np.zeros_like(r)]


def test_trim_leaves_the_disc_grown_by_the_distance(disc_support):
    """Faces within 0.1 of a disc of radius 0.5 remain: area ≈ π·0.6² (grid cell 0.025), every kept
    face's mean vertex distance < 0.1, every vertex referenced."""
    mesh = plane()
    out = trim_to_support(mesh, disc_support, 0.1)
    assert out.area == pytest.approx(np.pi * 0.6**2, rel=0.03)
    centre_r = np.linalg.norm(out.vertices[out.faces].mean(axis=1)[:, :2], axis=1)
    assert centre_r.max() < 0.6 + 0.025
    assert len(np.unique(out.faces)) == len(out.vertices)


def test_trim_off_or_nothing_to_remove_returns_the_mesh(disc_support):
    mesh = plane(half=0.3)
    assert trim_to_support(mesh, disc_support, 0.0) is mesh
    assert trim_to_support(mesh, disc_support, 0.1) is mesh


def test_trim_of_a_mesh_far_from_all_data_gives_none(disc_support):
    far = plane(half=0.2)
    far.vertices[:, 2] += 5.0
    assert trim_to_support(far, disc_support, 0.1) is None


def test_normal_trim_drops_a_parallel_sheet_but_keeps_the_rim_continuation():
    """Data on the square [−1, 1]² at z = 0 with upward planes. The mesh: the plane z = 0 over
    [−1.4, 1.4]² (0.4 past the data's rim in its own plane) and a sheet z = −0.3 under the data.
    The distance rule at 0.6 keeps both (the corners lie 0.57 from the data); along the normal at
    0.2 the sheet goes (0.3 from the data along the normal) and the rim continuation stays (0)."""
    from ultraboneudf.geometry.data_surface import DataSurface

    a = np.linspace(-1.0, 1.0, 41)
    xx, yy = np.meshgrid(a, a, indexing="ij")
    data = np.c_[xx.ravel(), yy.ravel(), np.zeros(xx.size)]
    surface = DataSurface(data, np.tile([0.0, 0.0, 1.0], (len(data), 1)), bridge=np.zeros(len(data)))
    top = plane(n=57, half=1.4)
    sheet = plane(n=21, half=0.5)
    sheet.vertices[:, 2] = -0.3
    mesh = trimesh.util.concatenate([top, sheet])
    assert trim_to_support(mesh, surface, 0.6) is mesh
    out = trim_to_support(mesh, surface, 0.6, max_normal=0.2)
    assert out.area == pytest.approx(top.area, rel=1e-9)
    assert np.abs(out.vertices[:, 2]).max() == 0.0
    # the normal rule alone, and no effect against bare points (no normals to measure along)
    assert trim_to_support(mesh, surface, 0.0, max_normal=0.2).area == pytest.approx(top.area, rel=1e-9)
    assert trim_to_support(mesh, data, 0.6, max_normal=0.2) is mesh


def square_sweep(gap_x: float = 0.0, gap_y: float = 0.0, bridge: float = 0.0, frames: bool = True):
    """Points every 0.05 on the square [−1, 1]² at z = 0 with upward planes, less the strips
    |x| < ``gap_x`` / 2 and |y| < ``gap_y`` / 2, as a DataSurface bridging gaps up to ``bridge``;
    with ``frames``, each row of constant y is a frame of a sweep along y (image planes x–z)."""
    from ultraboneudf.geometry.data_surface import DataSurface

    a = np.linspace(-1.0, 1.0, 41)
    xx, yy = np.meshgrid(a, a, indexing="ij")
    data = np.c_[xx.ravel(), yy.ravel(), np.zeros(xx.size)]
    row = np.rint((data[:, 1] + 1.0) / 0.05)
    keep = (np.abs(data[:, 0]) >= gap_x / 2) & (np.abs(data[:, 1]) >= gap_y / 2)
    data, row = data[keep], row[keep]
    sweep = {"frame_axis": np.tile([0.0, 1.0, 0.0], (len(data), 1)), "frame_order": row,
             "frame_bridge": 0.06} if frames else {}
    return DataSurface(data, np.tile([0.0, 0.0, 1.0], (len(data), 1)), bridge=np.full(len(data), bridge),
                       **sweep)


def test_rim_trim_stops_the_continuation_within_the_image_planes():
    """The plane z = 0 over [−1.4, 1.4]² on a sweep's data covering [−1, 1]²: the distance rule at
    0.6 keeps it all (its corners lie 0.57 from the data); at 0.2 past the rim within the image
    planes, it stops 0.2 past the frames' ends (|x| = 1) and goes on past the first and last frames
    (|y| = 1), where the probe did not look: 2.4 × 2.8, within a grid cell of 0.05 around the rim."""
    surface = square_sweep()
    mesh = plane(n=57, half=1.4)
    assert trim_to_support(mesh, surface, 0.6) is mesh
    out = trim_to_support(mesh, surface, 0.6, max_rim=0.2)
    assert out.area == pytest.approx(2.4 * 2.8, abs=2 * 2.8 * 0.05 / 2)
    centres = out.vertices[out.faces].mean(axis=1)
    assert np.abs(centres[:, 0]).max() < 1.2 + 0.025
    assert np.abs(centres[:, 1]).max() > 1.4 - 0.025
    # the rule alone; no effect without the frames, nor against bare points
    assert trim_to_support(mesh, surface, 0.0, max_rim=0.2).area == pytest.approx(out.area, rel=1e-9)
    assert trim_to_support(mesh, square_sweep(frames=False), 0.6, max_rim=0.2) is mesh
    assert trim_to_support(mesh, surface.points, 0.6, max_rim=0.2) is mesh


def test_rim_trim_opens_only_the_gaps_the_probe_looked_into():
    """A gap within the frames (|x| < 0.2) stays closed where bridged and opens where not (its
    middle lies 0.1 or more past either side's last echo); a gap across the frames (|y| < 0.2,
    frames lost) stays closed either way: the probe did not look there."""
    mesh = plane(n=41, half=1.0)
    assert trim_to_support(mesh, square_sweep(gap_x=0.4, bridge=0.5), 0.6, max_rim=0.05) is mesh
    out = trim_to_support(mesh, square_sweep(gap_x=0.4), 0.6, max_rim=0.05)
    centres = out.vertices[out.faces].mean(axis=1)
    assert np.abs(centres[:, 0]).min() > 0.1
    assert out.area < mesh.area - 2 * 0.1
    assert trim_to_support(mesh, square_sweep(gap_y=0.4), 0.6, max_rim=0.05) is mesh


def shelf():
    """The plane z = 0 over [−1, 1]² with a wall x = 1, z ∈ [−0.5, 0], hanging from its edge: a
    surface and a streak running on from its rim along the beams (−z)."""
    top = plane(n=41)
    a = np.linspace(-1.0, 1.0, 41)
    b = np.linspace(-0.5, 0.0, 11)
    yy, zz = np.meshgrid(a, b, indexing="ij")
    wall = trimesh.Trimesh(np.c_[np.ones(yy.size), yy.ravel(), zz.ravel()],
                           _grid_faces(41, 11), process=False)
    return top, wall


def _grid_faces(n: int, m: int) -> np.ndarray:
    """The triangles of an n × m grid of vertices numbered row-major."""
    idx = np.arange(n * m).reshape(n, m)
    q = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return np.r_[np.c_[q[0], q[1], q[2]], np.c_[q[0], q[2], q[3]]]


def test_grazing_trim_drops_the_streak_along_the_beams_and_keeps_the_surface_they_meet():
    """Echoes on the shelf of :func:`shelf` (top and wall) imaged from above (beams −z): the wall,
    which the beams meet side-on (90°), goes at 70°; the top (0°) stays. Tilted 30° off the beams,
    the wall (60°) stays. Beams of zero length, points farther than the radius and 0° judge
    nothing."""
    from ultraboneudf.extraction import grazing_faces

    top, wall = shelf()
    mesh = trimesh.util.concatenate([top, wall])
    on_wall = np.abs(mesh.triangles_center[:, 0] - 1.0) < 1e-9
    points = np.r_[top.vertices, wall.vertices]
    down = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    np.testing.assert_array_equal(grazing_faces(mesh, points, down, 0.2, 70.0), on_wall)
    tilted = np.tile([np.sin(np.radians(30.0)), 0.0, -np.cos(np.radians(30.0))], (len(points), 1))
    assert not grazing_faces(mesh, points, tilted, 0.2, 70.0).any()
    assert not grazing_faces(mesh, points, np.zeros_like(points), 0.2, 70.0).any()
    assert not grazing_faces(mesh, points + [0.0, 0.0, 5.0], down, 0.2, 70.0).any()
    assert not grazing_faces(mesh, points, down, 0.2, 0.0).any()


def test_grazing_trim_averages_the_beams_of_both_passes_over_a_face():
    """A face imaged by two passes, one meeting it head-on (beam −z) and one side-on (beam +x): their
    mean beam meets it at 45°, so it stays at 70°; the side-on pass alone drops it."""
    from ultraboneudf.extraction import grazing_faces

    top = plane(n=21, half=0.5)
    points = np.r_[top.vertices, top.vertices]
    beams = np.r_[np.tile([0.0, 0.0, -1.0], (len(top.vertices), 1)), np.tile([1.0, 0.0, 0.0], (len(top.vertices), 1))]
    assert not grazing_faces(top, points, beams, 0.2, 70.0).any()
    side_on = np.tile([1.0, 0.0, 0.0], (len(top.vertices), 1))
    assert grazing_faces(top, top.vertices, side_on, 0.2, 70.0).all()
