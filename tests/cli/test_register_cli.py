"""``ultraboneudf register``: the JSON record and pictures, ``--init``, and one-line refusals."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ultraboneudf.cli import main
from ultraboneudf.io import sha256_file
from ultraboneudf.registration import rigid

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "registration"))
from reg_shapes import lumpy_bone, mean_error, motion, one_sided_view  # noqa: E402

FAST = ["--set", "anchors=3", "--set", "turns=24", "--quiet"]


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("register")
    bone = lumpy_bone()
    truth = motion(35.0, (0.0, 1.0, 1.0), (20.0, 25.0, -30.0), bone.centroid)
    bone.export(folder / "ct.ply")
    np.save(folder / "target.npy", rigid.apply(truth, one_sided_view(bone)))
    return folder, bone, truth


@pytest.fixture(scope="module")
def first(case):
    """One search through the command line: (its exit code, the JSON)."""
    folder, _, _ = case
    code = main(["register", str(folder / "ct.ply"), str(folder / "target.npy"), "-o", str(folder / "t.json"),
                 "--png", str(folder / "t.png"), "--html", str(folder / "t.html"), *FAST])
    return code, json.loads((folder / "t.json").read_text())


def test_register_writes_the_record_and_the_pictures(case, first):
    folder, bone, truth = case
    code, data = first
    assert code == 0
    assert mean_error(np.array(data["transform"]), truth, bone) < 0.3
    assert {"kind", "transform", "transform_target_to_ct", "rotation_deg", "translation_mm", "residual_mm",
            "inlier_mm", "overlap", "coverage", "score", "confidence", "runner_up", "weakest_motion",
            "hypotheses", "timings", "counts", "seed", "options", "init", "version", "input"} == set(data)
    assert data["input"]["ct"] == {"path": str((folder / "ct.ply").resolve()), "sha256": sha256_file(folder / "ct.ply")}
    assert data["input"]["target"]["kind"] == "points"
    assert data["input"]["target"]["sha256"] == sha256_file(folder / "target.npy")
    assert data["options"]["anchors"] == 3 and data["options"]["grid_mm"] > 0 and data["seed"] == 0
    png = Image.open(folder / "t.png")
    assert png.width > png.height > 200
    assert "CT bone" in (folder / "t.html").read_text()


def test_register_from_an_earlier_record_or_landmarks(case, first, capsys):
    folder, bone, truth = case
    out = folder / "again.json"
    assert main(["register", str(folder / "ct.ply"), str(folder / "target.npy"), "-o", str(out),
                 "--init", str(folder / "t.json"), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert mean_error(np.array(data["transform"]), truth, bone) < 0.3
    assert data["confidence"] is None and data["hypotheses"] == 0
    assert data["input"]["init"]["kind"] == "matrix" and data["input"]["init"]["sha256"]
    assert "confidence none" in capsys.readouterr().out
    # three landmark pairs a few mm off, as picked by hand
    ct_marks = bone.vertices[[0, 500, 5000]]
    picked = rigid.apply(truth, ct_marks) + np.random.default_rng(0).normal(0.0, 2.0, (3, 3))
    np.savetxt(folder / "marks.txt", np.c_[ct_marks, picked])
    assert main(["register", str(folder / "ct.ply"), str(folder / "target.npy"), "-o", str(out),
                 "--init", str(folder / "marks.txt"), "--quiet"]) == 0     # replaces its own earlier record
    data = json.loads(out.read_text())
    assert mean_error(np.array(data["transform"]), truth, bone) < 0.3
    assert data["input"]["init"]["kind"] == "landmarks" and data["input"]["init"]["pairs"] == 3


@pytest.fixture()
def bad_files(case, tmp_path):
    folder, bone, _ = case
    (tmp_path / "foreign.json").write_text('{"mine": true}\n')
    (tmp_path / "shear.json").write_text(json.dumps([[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
    target = np.load(folder / "target.npy")
    nan = target.copy()
    nan[3] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    np.save(tmp_path / "micrometres.npy", target * 1000.0)
    np.savetxt(tmp_path / "cloud.xyz", target)
    return folder, tmp_path


@pytest.mark.parametrize("args, message", [
    (["missing.ply", "{target}", "-o", "out.json"], "missing.ply: no such"),
    (["{ct}", "missing.npy", "-o", "out.json"], "missing.npy: no such file"),
    (["cloud.xyz", "{target}", "-o", "out.json"], "cloud.xyz: "),
    (["{ct}", "{target}", "-o", "out.txt"], "must be a .json file"),
    (["{ct}", "{target}", "-o", "foreign.json"], "exists and is not an output of ultraboneudf"),
    (["{ct}", "{target}", "-o", "shear.json", "--init", "shear.json"], "is the input"),
    (["{ct}", "{target}", "-o", "out.json", "--init", "shear.json"], "not rigid"),
    (["{ct}", "{target}", "-o", "out.json", "--set", "anchor=3"], "unknown registration option 'anchor'"),
    (["{ct}", "{target}", "-o", "out.json", "--set", "turns=0"], "turns"),
    (["{ct}", "{target}", "-o", "out.json", "--png", "out.jpg"], "--png writes .png"),
    (["{ct}", "{ct}", "-o", "out.json", "--units", "m"], "--units applies to point cloud files"),
    (["{ct}", "{target}", "-o", "out.json", "--mesh", "r.ply"], "--mesh applies to a tracked sweep"),
    (["{ct}", "{target}", "-o", "out.json", "--threads", "0"], "--threads"),
    (["{ct}", "nan.npy", "-o", "out.json"], "NaN"),
    (["{ct}", "micrometres.npy", "-o", "out.json"], "micrometres"),
])
def test_register_refuses_bad_input_in_one_line(bad_files, monkeypatch, capsys, args, message):
    folder, here = bad_files
    monkeypatch.chdir(here)
    args = [a.format(ct=folder / "ct.ply", target=folder / "target.npy") for a in args]
    assert main(["register", *args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (here / "out.json").exists() and not (here / "out.jpg").exists() and not (here / "r.ply").exists()
    assert (here / "foreign.json").read_text() == '{"mine": true}\n'


@pytest.fixture(scope="module")
def sweep(case):
    """A simulated tracked sweep over the CT bone, in the CT's own frame (the true pose: identity)."""
    from ultraboneudf.synth.simulator import config_with_noise, simulate_sweep

    folder, bone, _ = case
    sim = simulate_sweep(bone, config_with_noise("moderate", width_px=128, height_px=160, spacing_mm=0.4, seed=1))
    sim.write(folder / "sweep")
    return folder / "sweep"


def test_register_to_a_sweeps_points(case, sweep):
    folder, bone, _ = case
    out = folder / "sweep.json"
    assert main(["register", str(folder / "ct.ply"), str(sweep), "-o", str(out), "--no-reconstruct", *FAST]) == 0
    data = json.loads(out.read_text())
    assert mean_error(np.array(data["transform"]), np.eye(4), bone) < 0.5
    target = data["input"]["target"]
    assert target["kind"] == "sweep points" and target["sweep"]["frames"] > 100 and target["sha256"]


@pytest.mark.slow
def test_register_to_a_sweeps_reconstruction(case, sweep):
    folder, bone, _ = case
    out, mesh = folder / "recon.json", folder / "recon.ply"
    assert main(["register", str(folder / "ct.ply"), str(sweep), "-o", str(out), "--mesh", str(mesh),
                 "--iters", "2000", "--device", "cpu", *FAST]) == 0
    data = json.loads(out.read_text())
    assert mean_error(np.array(data["transform"]), np.eye(4), bone) < 0.5
    target = data["input"]["target"]
    assert target["kind"] == "sweep reconstruction" and target["reconstruction"]["config"]["train"]["iters"] == 2000
    assert mesh.exists() and (folder / "recon.ply.json").exists()
