"""benchmarks/bench_real.py: the scores against the CT as given and as registered to the points."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from ultraboneudf import load_mesh

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_real.py"


@pytest.fixture(scope="module")
def bench_real():
    spec = importlib.util.spec_from_file_location("bench_real", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def misregistered(tmp_path_factory):
    """An ellipsoid 'CT' (mm) and points on it in a frame turned by 1.5° and shifted by 1 mm: the
    data's CT registration off as on the real clouds."""
    ct = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    ct.apply_scale([40.0, 25.0, 15.0])
    path = tmp_path_factory.mktemp("ct") / "bone_ct.stl"
    ct.export(path)
    points, _ = trimesh.sample.sample_surface(ct, 6000, seed=3)
    return path, np.asarray(_misregister(points)), ct


def _misregister(x: np.ndarray) -> np.ndarray:
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    return Rotation.from_rotvec(np.radians(1.5) * axis).apply(x) + [1.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def truths(bench_real, misregistered):
    """The CT as given and as registered to the points, with the registration's motion."""
    path, points, _ = misregistered
    truth = bench_real.Truth(path, points, samples=200_000)
    registered, motion = bench_real.registered_truth(truth.mesh, points, seed=0)
    return truth, registered, motion


def test_the_registered_ct_takes_out_the_frames_error(misregistered, truths):
    path, points, ct = misregistered
    truth, registered, motion = truths
    assert motion["reg_turn_deg"] == pytest.approx(1.5, abs=0.2)
    assert motion["reg_shift_mm"] == pytest.approx(np.linalg.norm(_misregister(ct.vertices) - ct.vertices, axis=1).mean(),
                                                   abs=0.1)
    given = load_mesh(path).vertices  # the file's vertices, in the order the registered CT keeps
    assert np.abs(registered.mesh.vertices - _misregister(given)).max() < 0.1
    as_given, as_registered = truth.score(points), registered.score(points)
    assert as_registered["cd_mm"] < as_given["cd_mm"] - 0.2


def test_a_mesh_row_carries_both_scores(bench_real, misregistered, truths):
    _, _, ct = misregistered
    truth, registered, _ = truths
    mesh = trimesh.Trimesh(_misregister(ct.vertices), ct.faces)  # the bone itself, in the points' frame
    row = bench_real.mesh_scores(truth, mesh, 50_000, None, registered)
    assert row["pieces"] == 1
    assert row["reg_cd_mm"] < 0.2 < row["cd_mm"]  # 0.2: the spacing of the CT's samples
    assert row["reg_covered"] == row["reg_on_bone"] == 1.0
    assert {f"reg_{k}" for k in bench_real.REGISTERED} <= set(row)


def _slices(rng, count=12, per=60, radius=12.0):
    """A cylinder's upper half (axis z, radius mm) imaged from above in ``count`` planes z = const,
    each frame's points together and in random order, as a compounded cloud keeps them."""
    frames = []
    for z in np.linspace(-20.0, 20.0, count):
        phi = rng.uniform(np.radians(10), np.radians(170), per)  # the arc a probe above sees
        frames.append(np.column_stack([radius * np.cos(phi), radius * np.sin(phi), np.full(per, z)]))
    return frames


def test_oblique_faces_offset_by_incidence(bench_real, tmp_path):
    """Points pushed out of a cylinder by 2 × (1 − cos incidence): the by-incidence medians follow,
    with the beam known (straight down), estimated from the frames, and told by a row-by-row order."""
    frames = _slices(np.random.default_rng(2), per=200)
    points = np.concatenate(frames)
    radial = points[:, :2] / np.linalg.norm(points[:, :2], axis=1, keepdims=True)
    cos = np.abs(radial[:, 1])                      # the beam is along −y
    pushed = points.copy()
    pushed[:, :2] += (2.0 * (1.0 - cos))[:, None] * radial
    ct = trimesh.creation.cylinder(radius=12.0, height=60.0, sections=256).subdivide_to_size(1.0)
    path = tmp_path / "cyl_ct.stl"
    ct.export(path)
    truth = bench_real.Truth(path, pushed, samples=400_000)
    signed, normals = truth.signed(pushed, with_normals=True)
    known = bench_real.by_incidence(signed, normals, np.tile([0.0, -1.0, 0.0], (len(pushed), 1)))
    angle = np.degrees(np.arccos(cos))
    assert len(known) == 6
    for bin_, row in known.items():
        lo = float(bin_.split("-")[0])
        inside = (angle >= lo) & (angle < lo + 15)
        assert row["points"] == pytest.approx(inside.sum(), rel=0.1)  # the CT is faceted
        assert row["median_mm"] == pytest.approx(np.median(2.0 * (1.0 - cos[inside])), abs=0.1)
    info = bench_real.describe(pushed, truth)
    assert info["beams"] == "frames"
    assert info["by_incidence"]["75-90"]["median_mm"] > 1.2 > 0.2 > info["by_incidence"]["0-15"]["median_mm"]
    # the same frames on a pixel grid, each written row by row from the probe down: their order
    # tells the beam itself, and every bin follows the push as with the beam known
    rows = []
    for z in np.unique(pushed[:, 2]):
        pixels = np.unique(np.rint(pushed[pushed[:, 2] == z][:, :2] / [0.3, 0.08]), axis=0) * [0.3, 0.08]
        pixels = pixels[np.lexsort((pixels[:, 0], -pixels[:, 1]))]
        rows.append(np.column_stack([pixels, np.full(len(pixels), z)]))
    written = np.concatenate(rows)
    info = bench_real.describe(written, bench_real.Truth(path, written, samples=400_000))
    assert info["beams"] == "order"
    for bin_, row in info["by_incidence"].items():
        assert row["median_mm"] == pytest.approx(known[bin_]["median_mm"], abs=0.1)


def test_the_principal_pose_is_rigid_and_follows_the_cloud(bench_real):
    """A cloud turned and moved anyhow is brought to the same principal-axes image, by a rigid
    motion."""
    rng = np.random.default_rng(5)
    # a skewed, anisotropic cloud: part of an ellipsoid's surface and a cluster off one side
    shell = rng.normal(size=(4000, 3))
    shell = shell / np.linalg.norm(shell, axis=1, keepdims=True) * [40.0, 20.0, 8.0]
    cloud = np.vstack([shell[(shell[:, 0] > -10) & (shell[:, 1] > -5)], rng.normal([30, 15, 0], 2.0, (300, 3))])
    turned = Rotation.from_euler("zyx", [110, -48, 17], degrees=True).apply(cloud) + [300.0, -20.0, 1500.0]
    a, b = bench_real.principal_pose(cloud), bench_real.principal_pose(turned)
    for m in (a, b):
        assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
    image_a, image_b = trimesh.transform_points(cloud, a), trimesh.transform_points(turned, b)
    np.testing.assert_allclose(image_a, image_b, atol=1e-6)
    np.testing.assert_allclose(image_a.mean(axis=0), 0.0, atol=1e-9)
    spread = image_a.std(axis=0)
    assert spread[0] > spread[1] > spread[2]


def test_a_sparser_cloud_is_a_fixed_ordered_subset(bench_real):
    """--points: n distinct points of the cloud, in their order, the same draw every time; the whole
    cloud when n is not smaller."""
    cloud = np.random.default_rng(5).normal(size=(1000, 3))
    part = bench_real.sparser(cloud, 300)
    assert part.shape == (300, 3)
    rows = [int(np.flatnonzero((cloud == p).all(axis=1))[0]) for p in part]
    assert rows == sorted(set(rows))
    np.testing.assert_array_equal(part, bench_real.sparser(cloud, 300))
    assert bench_real.sparser(cloud, 1000) is cloud


def test_every_kth_frame_keeps_whole_frames(bench_real):
    """--cloud-frame-step 3 on twelve slices: the points of slices 0, 3, 6 and 9, in their order."""
    frames = _slices(np.random.default_rng(2))
    kept = bench_real.every_kth_frame(np.concatenate(frames), 3)
    planes = np.unique(kept[:, 2])
    np.testing.assert_allclose(planes, np.linspace(-20.0, 20.0, 12)[[0, 3, 6, 9]])
    assert len(kept) > 0.98 * 4 * len(frames[0])
    np.testing.assert_array_equal(np.diff(kept[:, 2]) >= 0, True)
