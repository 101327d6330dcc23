"""Outputs never cost the user data: no input, foreign file or other mesh's sidecar is replaced,
and a mesh is never left without its sidecar."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from ultraboneudf.cli import main
from ultraboneudf.errors import InputError
from ultraboneudf.io import WriteError, check_outputs, save_mesh_with_sidecar, sidecar_path

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
    assert src.read_bytes() == before and not (tmp_path / "good.ply.json").exists()
    # nor any file inside a sweep folder being read
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    with pytest.raises(InputError, match="inside the input folder"):
        check_outputs(sweep / "bone.ply", (sweep,))


def test_a_foreign_file_is_never_replaced(tmp_path, capsys):
    src = _cloud_ply(tmp_path / "in.ply")
    folder = tmp_path / "sweep"
    folder.mkdir()
    # the sidecar of calibration.ply is calibration.ply.json, never the sweep's calibration.json
    calibration = folder / "calibration.json"
    calibration.write_text('{"rotation": [1, 2, 3]}')
    assert main(["reconstruct", str(src), "-o", str(folder / "calibration.ply"), *FAST]) == 0
    assert calibration.read_text() == '{"rotation": [1, 2, 3]}'
    assert json.loads((folder / "calibration.ply.json").read_text())["mesh"] == "calibration.ply"
    capsys.readouterr()
    # a file of someone else's at the sidecar's name is not replaced
    theirs = folder / "knee.ply.json"
    theirs.write_text('{"notes": "mine"}')
    assert main(["reconstruct", str(src), "-o", str(folder / "knee.ply"), *FAST]) == 2
    _one_error(capsys, "knee.ply.json", "not a sidecar of ultraboneudf")
    assert theirs.read_text() == '{"notes": "mine"}' and not (folder / "knee.ply").exists()
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
    first = json.loads((tmp_path / "bone.ply.json").read_text())
    assert first["mesh"] == "bone.ply"
    assert main(["reconstruct", str(src), "-o", str(out), *FAST, "--seed", "7"]) == 0   # a rerun
    assert json.loads((tmp_path / "bone.ply.json").read_text())["seed"] == 7
    # bone.obj beside bone.ply: each mesh has its own sidecar
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "bone.obj"), *FAST]) == 0
    assert json.loads((tmp_path / "bone.obj.json").read_text())["mesh"] == "bone.obj"
    assert json.loads((tmp_path / "bone.ply.json").read_text())["mesh"] == "bone.ply"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bone.obj", "bone.obj.json", "bone.ply",
                                                          "bone.ply.json", "in.ply"]


def test_an_output_with_an_earlier_versions_sidecar_is_recognised(tmp_path):
    """Earlier versions named the sidecar NAME.json: such a pair is an earlier output, replaced as a
    unit (the old sidecar removed once the new pair is in place); a NAME.json describing another
    mesh is left alone."""
    mesh = tmp_path / "bone.ply"
    trimesh.creation.box().export(mesh)
    old = tmp_path / "bone.json"
    old.write_text(json.dumps({**SIDECAR, "mesh": "bone.ply"}))
    assert check_outputs(mesh) == mesh
    save_mesh_with_sidecar(trimesh.creation.icosahedron(), mesh, SIDECAR)
    assert not old.exists() and json.loads(sidecar_path(mesh).read_text())["mesh"] == "bone.ply"
    # bone.json of bone.ply does not make bone.obj an output of ours, nor is it removed for it
    obj = tmp_path / "bone.obj"
    trimesh.creation.box().export(obj)
    old.write_text(json.dumps({**SIDECAR, "mesh": "bone.ply"}))
    with pytest.raises(InputError, match="not an output of ultraboneudf"):
        check_outputs(obj)
    obj.unlink()
    save_mesh_with_sidecar(trimesh.creation.icosahedron(), obj, SIDECAR)
    assert json.loads(old.read_text())["mesh"] == "bone.ply"


@pytest.mark.parametrize("failure", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_a_failure_between_the_two_files_leaves_the_earlier_pair(tmp_path, monkeypatch, failure):
    """The mesh is renamed into place first and the sidecar last; a full disk or Ctrl-C at the
    sidecar's rename puts the earlier pair back (here: none) and removes every staged file. A full
    disk is a failure after the work (``WriteError``: exit 1), not a refusal."""
    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append(os.path.basename(dst))
        if str(dst).endswith(".ply.json"):
            raise failure
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    out = tmp_path / "m.ply"
    expected = WriteError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected):
        save_mesh_with_sidecar(trimesh.creation.icosahedron(), out, SIDECAR)
    assert calls[-2:] == ["m.ply", "m.ply.json"]
    assert list(tmp_path.iterdir()) == []


def _drop_root_file_privileges() -> None:
    """In the child before it runs: without CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH in its
    bounding set, root meets file permissions as any user does (the suite runs as root in CI)."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    for capability in (1, 2):  # CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH
        if libc.prctl(24, capability, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            os._exit(97)


def _error_without_privileges(*args: str) -> str:
    """The command line run as a user without root's file privileges: exit 2 and its one line."""
    res = subprocess.run([sys.executable, "-m", "ultraboneudf.cli", *args], capture_output=True, text=True,
                         preexec_fn=_drop_root_file_privileges if os.geteuid() == 0 else None)
    if res.returncode == 97:
        pytest.skip("cannot drop root's file privileges here (no CAP_SETPCAP)")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "Traceback" not in res.stderr, res.stderr
    return lines[0]


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX permissions")
def test_a_read_only_folder_is_one_line_before_any_work(tmp_path):
    src = _cloud_ply(tmp_path / "in.ply")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        line = _error_without_privileges("reconstruct", str(src), "-o", str(locked / "m.ply"), *FAST)
    finally:
        locked.chmod(0o755)
    assert "cannot write into" in line and "permission denied" in line
    assert list(locked.iterdir()) == []


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="POSIX permissions")
def test_an_unreadable_input_is_one_line_before_any_work(tmp_path):
    src = _cloud_ply(tmp_path / "locked.ply")
    src.chmod(0o000)
    try:
        line = _error_without_privileges("reconstruct", str(src), "-o", str(tmp_path / "m.ply"), *FAST)
    finally:
        src.chmod(0o644)
    assert "locked.ply" in line and "Permission denied" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["locked.ply"]


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
    side = json.loads((tmp_path / "m.ply.json").read_text())
    assert side["input"]["units"] == unit
    lo, hi = trimesh.load(tmp_path / "m.ply").bounds
    assert 20 < (hi - lo).max() < 60                 # the mesh is in mm
    with pytest.raises(InputError, match="beyond"):
        from ultraboneudf.io import check_units
        check_units(np.array([[0.0, 0.0, 0.0], [2e6, 1.0, 1.0]]))


def test_a_folder_output_is_replaced_only_when_every_file_in_it_is_ours(tmp_path, monkeypatch):
    """A folder output (a simulation, a demo, a dataset) lists its files in ultraboneudf.json: it is
    replaced as a whole while they are there unchanged; a file added or edited by the user stops it
    (``--overwrite`` replaces it anyway); an empty folder is simply used; the current folder never."""
    from ultraboneudf.io import check_output, write_folder_output
    from ultraboneudf.io.outputs import record

    out = tmp_path / "sim"

    def fill(text):
        return lambda folder: ((folder / "frames").mkdir(), (folder / "frames" / "0.png").write_text(text))

    write_folder_output(out, fill("first"), record("test"))
    assert check_output(out, kind="folder") == out
    write_folder_output(out, fill("second"), record("test"))
    assert (out / "frames" / "0.png").read_text() == "second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]          # no backup, no staging left
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="notes.txt: in .* but not written by ultraboneudf"):
        check_output(out, kind="folder")
    (out / "notes.txt").unlink()
    (out / "frames" / "0.png").write_text("edited")
    with pytest.raises(InputError, match="0.png: changed since ultraboneudf wrote it"):
        check_output(out, kind="folder")
    assert check_output(out, kind="folder", overwrite=True) == out
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_output(empty, kind="folder") == empty
    monkeypatch.chdir(out)
    with pytest.raises(InputError, match="is the current folder"):
        check_output(out, kind="folder", overwrite=True)


def test_names_the_file_system_cannot_hold_and_special_files_are_refused(tmp_path):
    """Before any work: a name whose sidecar's name is too long, a path through a file, a named pipe
    at the output's name, a folder where a file goes."""
    from ultraboneudf.io import check_output

    with pytest.raises(InputError, match=r"the name of its sidecar .* is 259 bytes long, more than the 255"):
        check_output(tmp_path / ("b" * 250 + ".ply"))
    with pytest.raises(InputError, match=r"is 256 bytes long"):
        check_output(tmp_path / ("b" * 252 + ".ply"))
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        check_output(tmp_path / "file" / "out.ply")
    os.mkfifo(tmp_path / "pipe.png")
    with pytest.raises(InputError, match="is a named pipe"):
        check_output(tmp_path / "pipe.png", overwrite=True)
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        check_output(tmp_path / "dir.png", overwrite=True)


def test_a_disk_with_too_little_room_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    import shutil

    from ultraboneudf.io.outputs import FREE_SPACE_BYTES

    src = _cloud_ply(tmp_path / "in.ply")
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=FREE_SPACE_BYTES // 2))
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "m.ply"), *FAST]) == 2
    _one_error(capsys, "only 32 MB free", "need at least 64 MB")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.ply"]
