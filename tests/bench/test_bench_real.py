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
