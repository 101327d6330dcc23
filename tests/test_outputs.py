"""Outputs never cost the user data: no input, foreign file or other mesh's sidecar is replaced,
and a mesh is never left without its sidecar."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh

from ultraboneudf.cli import main
from ultraboneudf.errors import InputError
from ultraboneudf.io import check_outputs, save_mesh_with_sidecar

FAST = ["--preset", "fast", "--iters", "200", "--set", "train.batch=1000", "--set", "extract.max_depth=6",
        "--set", "model.hidden=32,32", "--quiet"]
SIDECAR = {"method": "ultraboneudf", "config": {}, "version": "test"}


def _cloud_ply(path, n=2000):
    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, n)
    pts = np.c_[20 * np.cos(theta), rng.uniform(0, 40, n), 20 * np.sin(theta)]
    trimesh.PointCloud(pts).export(path)
    return path


def _one_error(capsys, *fragments):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ultraboneudf reconstruct: error: "), err
    for text in fragments:
        assert text in err[0], err[0]


def test_the_input_is_never_the_output(tmp_path, capsys):
    src = _cloud_ply(tmp_path / "good.ply")
    before = src.read_bytes()
    assert main(["reconstruct", str(src), "-o", str(src), *FAST]) == 2
    _one_error(capsys, "good.ply", "is the input")
    assert src.read_bytes() == before and not (tmp_path / "good.json").exists()
    # nor any file inside a sweep folder being read
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    with pytest.raises(InputError, match="inside the input folder"):
        check_outputs(sweep / "bone.ply", (sweep,))


def test_a_foreign_file_is_never_replaced(tmp_path, capsys):
    src = _cloud_ply(tmp_path / "in.ply")
    folder = tmp_path / "sweep"
    folder.mkdir()
    calibration = folder / "calibration.json"
    calibration.write_text('{"rotation": [1, 2, 3]}')
    assert main(["reconstruct", str(src), "-o", str(folder / "calibration.ply"), *FAST]) == 2
    _one_error(capsys, "calibration.json", "not a sidecar of ultraboneudf")
    assert calibration.read_text() == '{"rotation": [1, 2, 3]}'
    assert not (folder / "calibration.ply").exists()
    # a mesh the user made (no sidecar of ours) is not replaced either
    theirs = tmp_path / "bone.ply"
    trimesh.creation.box().export(theirs)
    before = theirs.read_bytes()
    assert main(["reconstruct", str(src), "-o", str(theirs), *FAST]) == 2
    _one_error(capsys, "bone.ply", "not an output of ultraboneudf")
    assert theirs.read_bytes() == before


def test_an_earlier_output_is_replaced_as_a_unit_and_sidecars_do_not_clash(tmp_path, capsys):
    src = _cloud_ply(tmp_path / "in.ply")
    out = tmp_path / "bone.ply"
    assert main(["reconstruct", str(src), "-o", str(out), *FAST]) == 0
    first = json.loads(out.with_suffix(".json").read_text())
    assert first["mesh"] == "bone.ply"
    assert main(["reconstruct", str(src), "-o", str(out), *FAST, "--seed", "7"]) == 0   # a rerun
    assert json.loads(out.with_suffix(".json").read_text())["seed"] == 7
    capsys.readouterr()
    # bone.obj would share bone.json with bone.ply: refused before any work
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "bone.obj"), *FAST]) == 2
    _one_error(capsys, "bone.json", "is the sidecar of bone.ply")
    assert not (tmp_path / "bone.obj").exists()
    assert json.loads(out.with_suffix(".json").read_text())["mesh"] == "bone.ply"


@pytest.mark.parametrize("failure", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_a_failure_between_the_two_files_leaves_neither(tmp_path, monkeypatch, failure):
    """The mesh is renamed into place first and the sidecar last; a failure or Ctrl-C at the
    sidecar's rename removes the mesh again and every temporary file."""
    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append(dst)
        if str(dst).endswith(".json"):
            raise failure
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    out = tmp_path / "m.ply"
    expected = InputError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected):
        save_mesh_with_sidecar(trimesh.creation.icosahedron(), out, SIDECAR)
    assert [str(c) for c in calls] == [str(out), str(out.with_suffix(".json"))]
    assert list(tmp_path.iterdir()) == []


def test_sigterm_while_committing_leaves_neither(tmp_path):
    """A SIGTERM between the two renames (a slow disk, the process killed by a scheduler) removes
    the mesh already in place."""
    out = tmp_path / "m.ply"
    script = f"""
import os, sys, time, trimesh
from ultraboneudf import io
real = os.replace
def slow(src, dst):
    if str(dst).endswith('.json'):
        print('between', flush=True)
        time.sleep(30)
    real(src, dst)
os.replace = slow
io.save_mesh_with_sidecar(trimesh.creation.icosahedron(), {str(out)!r}, {SIDECAR!r})
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "between"
    assert out.exists()                     # the mesh is in place, its sidecar not yet
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=20) == 128 + signal.SIGTERM
    time.sleep(0.1)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_one_line_before_any_work(tmp_path, capsys):
    src = _cloud_ply(tmp_path / "in.ply")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        assert main(["reconstruct", str(src), "-o", str(locked / "m.ply"), *FAST]) == 2
        _one_error(capsys, "permission denied")
    finally:
        locked.chmod(0o755)


@pytest.mark.parametrize("scale,unit,hint", [(0.001, "m", "--units m"), (1000.0, "um", "--units um")])
def test_a_cloud_in_the_wrong_unit_is_one_line_before_any_work(tmp_path, capsys, scale, unit, hint):
    """A femur-sized patch (40 mm) written in metres or micrometres is refused with the unit it looks
    like; ``--units`` converts it and the run goes through, recorded in the sidecar."""
    cloud = trimesh.load(_cloud_ply(tmp_path / "mm.ply")).vertices * scale
    src = tmp_path / f"in_{unit}.xyz"
    np.savetxt(src, cloud)
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "m.ply"), *FAST]) == 2
    _one_error(capsys, src.name, hint)
    assert not (tmp_path / "m.ply").exists()
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "m.ply"), "--units", unit, *FAST]) == 0
    side = json.loads((tmp_path / "m.json").read_text())
    assert side["input"]["units"] == unit
    lo, hi = trimesh.load(tmp_path / "m.ply").bounds
    assert 20 < (hi - lo).max() < 60                 # the mesh is in mm
    with pytest.raises(InputError, match="beyond"):
        from ultraboneudf.io import check_units
        check_units(np.array([[0.0, 0.0, 0.0], [2e6, 1.0, 1.0]]))
