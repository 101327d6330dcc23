"""Datasets as manifests, the resumable experiment runner and its tables."""

import base64
import re
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from ultraboneudf.bench.datasets import make_dataset
from ultraboneudf.bench.manifest import read_manifest
from ultraboneudf.bench.report import html_report, report, swept_axis
from ultraboneudf.bench.runner import EXPERIMENTS, finished_rows, plan, run_cells
from ultraboneudf.cli import main
from ultraboneudf.errors import InputError

QUICK = ["train.iters=150", "train.batch=500", "extract.max_depth=6", "model.hidden=32,32"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    (root / "bones").mkdir()
    trimesh.creation.icosphere(subdivisions=3, radius=20.0).export(root / "bones" / "ball.ply")
    trimesh.creation.capsule(height=40, radius=10).export(root / "bones" / "capsule.ply")
    return make_dataset("openbone", root / "bones", root / "ds", samples=2000)


def test_openbone_units_are_the_upward_faces_sampled(dataset):
    units = read_manifest(dataset)
    assert [u.id for u in units] == ["ball", "capsule"] and all(u.pseudo_gt_mm is None for u in units)
    ball = units[0]
    points = np.load(ball.input)["points"]
    gt = trimesh.load(ball.gt, process=False)
    assert points.shape == (2000, 3)
    assert (gt.face_normals[:, 2] > 0).all()                             # the part a probe above sees
    assert gt.area == pytest.approx(2 * np.pi * 20.0 ** 2, rel=0.05)     # a hemisphere
    assert np.abs(np.linalg.norm(points, axis=1) - 20.0).max() < 0.3 and points[:, 2].min() > -1.0


def test_manifest_errors_name_the_file_and_line(tmp_path, dataset):
    bad = tmp_path / "m.csv"
    bad.write_text("id,specimen,input\nx,y,z\n")
    with pytest.raises(InputError, match=r"m.csv: the manifest needs the columns .* \(missing: gt\)"):
        read_manifest(bad)
    text = dataset.read_text().splitlines()
    bad.write_text("\n".join([text[0], text[1], text[1]]) + "\n")
    (tmp_path / "ball.npz").write_bytes((dataset.parent / "ball.npz").read_bytes())
    (tmp_path / "ball_gt.ply").write_bytes((dataset.parent / "ball_gt.ply").read_bytes())
    with pytest.raises(InputError, match="line 3: duplicate id 'ball'"):
        read_manifest(bad)
    bad.write_text(text[0] + "\nball,ball,nothing.npz,ball_gt.ply,\n")
    with pytest.raises(InputError, match="line 2: input 'nothing.npz' does not exist"):
        read_manifest(bad)


def test_the_experiments_expand_to_the_papers_grids(dataset):
    units = read_manifest(dataset)
    e5 = plan(units, "E5", [], [], [], "robust", 0)
    assert len(e5) == 2 * 16 and all("loss.kind=pull" in c.overrides for c in e5)
    assert len({c.id for c in e5}) == len(e5)
    assert len(plan(units, "E1", [], [], [], "robust", 0)) == 2 * 5
    assert {c.method for c in plan(units, "E7", [], [], [], "robust", 0)} == set(EXPERIMENTS["E7"]["methods"])
    grid = plan(units, None, ["ultraboneudf", "poisson"], ["loss.lambda_gs=0,0.1", "train.lr=0.001,0.002"], [], "fast", 3)
    assert len(grid) == 2 * 2 * 2 * 2      # units × methods × the two axes
    with pytest.raises(InputError, match="unknown experiment 'E9'"):
        plan(units, "E9", [], [], [], "robust", 0)


def test_a_killed_run_resumes_without_recomputing_finished_cells(dataset, tmp_path):
    units = read_manifest(dataset)
    cells = plan(units, None, ["ultraboneudf"], ["loss.lambda_gs=0,0.01"], QUICK, "fast", 0)
    out = tmp_path / "run"
    assert run_cells(cells, out, device="cpu", samples=5000) == {"done": 4, "skipped": 0, "failed": 0}
    rows = finished_rows(out)
    assert len(rows) == 4 and all(r["status"] == "ok" and r["cd_mm"] < 2.0 for r in rows)
    assert (out / "results.csv").read_text().count("\n") == 5
    # a cell killed half-way: its mesh written, its result not — it is not finished
    victim = out / "cells" / cells[1].id
    first = json.loads((victim / "result.json").read_text())
    (victim / "result.json").unlink()
    (victim / "mesh.ply").write_bytes(b"half a mesh")
    assert run_cells(cells, out, device="cpu", samples=5000) == {"done": 1, "skipped": 3, "failed": 0}
    again = json.loads((victim / "result.json").read_text())
    assert again["cd_mm"] == pytest.approx(first["cd_mm"], rel=1e-6)       # the same cell, recomputed
    import sqlite3

    with sqlite3.connect(out / "results.sqlite") as db:
        assert db.execute("SELECT COUNT(*), SUM(status = 'ok') FROM cells").fetchone() == (4, 4)
    table = report(out)
    assert "ultraboneudf [loss.lambda_gs=0]" in table and "**" in table and "train.iters" not in table
    assert "Parameters and runtime" in table and "| 1282 |" in table   # (32, 32) with weight norm: 1,282
    # the HTML page: the same tables, CD against the swept setting, a picture per unit
    axis, series = swept_axis(rows)
    assert axis == "loss.lambda_gs" and list(series) == ["ultraboneudf"]
    rows = finished_rows(out)
    means = {x: np.mean([r["cd_mm"] for r in rows if f"loss.lambda_gs={x:g}" in r["overrides"].split()])
             for x in (0, 0.01)}
    assert series["ultraboneudf"] == [pytest.approx((0.0, means[0])), pytest.approx((0.01, means[0.01]))]
    page = html_report(out)
    assert page.startswith("<!DOCTYPE html>") and page.count("<table>") == 3 and "<b>" in page
    assert "<svg" in page and page.count("<polyline") == 1
    assert page.count('src="data:image/png;base64,') == 2                 # ball and capsule
    png = base64.b64decode(page.split('src="data:image/png;base64,')[1].split('"')[0])
    assert png.startswith(b"\x89PNG")


def test_cli_bench_dataset_run_report(tmp_path, capsys):
    bones = tmp_path / "bones"
    bones.mkdir()
    trimesh.creation.icosphere(subdivisions=3, radius=15.0).export(bones / "ball.ply")
    assert main(["bench", "dataset", "closedbone", str(bones), "--out", str(tmp_path / "ds"),
                 "--samples", "2000", "--quiet"]) == 0
    args = ["bench", "run", "--dataset", str(tmp_path / "ds" / "manifest.csv"), "--out", str(tmp_path / "r"),
            "--method", "ultraboneudf", "--preset", "fast", "--device", "cpu", "--samples", "5000", "--quiet"]
    for item in QUICK:
        args += ["--set", item]
    assert main(args) == 0
    assert main(args) == 0
    assert "0 cells done, 0 failed, 1 finished before" in capsys.readouterr().out
    page = tmp_path / "report.html"
    assert main(["bench", "report", str(tmp_path / "r"), "--format", "csv", "--html", str(page)]) == 0
    assert "ball" in capsys.readouterr().out
    assert "<table>" in page.read_text() and "data:image/png;base64," in page.read_text()
    assert main([*args[:-2], "--set", "loss.kind=bogus"]) == 2              # checked before any cell


def test_a_users_folder_of_pairs_becomes_a_manifest(tmp_path):
    folder = tmp_path / "scans"
    folder.mkdir()
    np.savetxt(folder / "knee1.xyz", np.random.default_rng(0).normal(size=(200, 3)) * 10)
    trimesh.creation.icosphere(radius=10).export(folder / "knee1_gt.stl")
    np.savetxt(folder / "orphan.xyz", np.zeros((5, 3)))                  # no ground truth: left out
    manifest = make_dataset("pairs", folder, tmp_path / "ds")
    units = read_manifest(manifest)
    assert [(u.id, u.input.name, u.gt.name) for u in units] == [("knee1", "knee1.xyz", "knee1_gt.stl")]
    with pytest.raises(InputError, match="no NAME.<cloud> with a NAME_gt.<mesh>"):
        make_dataset("pairs", tmp_path / "ds", tmp_path / "ds2")


def test_a_pool_of_two_workers_gives_the_same_table_as_one(dataset, tmp_path):
    units = read_manifest(dataset)
    cells = plan(units, None, ["ultraboneudf"], [], QUICK, "fast", 0)
    one, two = tmp_path / "one", tmp_path / "two"
    # the pool gives each worker its share of the CPU threads; float sums depend on the thread count,
    # so the one-process run uses the same count
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // 2))
    try:
        run_cells(cells, one, device="cpu", samples=5000)
    finally:
        torch.set_num_threads(threads)
    assert run_cells(cells, two, device="cpu", samples=5000, workers=2) == {"done": 2, "skipped": 0, "failed": 0}
    strip = lambda rows: [{k: v for k, v in r.items() if not k.endswith("_s")} for r in rows]  # noqa: E731
    assert strip(finished_rows(one)) == strip(finished_rows(two))


FEMUR = Path(__file__).resolve().parents[3] / "shared" / "data" / "bones" / "femur.ply"


@pytest.mark.skipif(not FEMUR.exists(), reason=f"{FEMUR} not present")
def test_the_gpu_check_runs_on_the_cpu_in_quick_mode(tmp_path):
    """benchmarks/gpu_check.py, ready for a GPU session, with tiny budgets on the CPU: every stage
    runs and reports (the numbers mean nothing)."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"
    out, real = tmp_path / "out", tmp_path / "real"
    real.mkdir()
    ct = trimesh.creation.icosphere(4, radius=30.0)        # a "CT" bone and its upper half as the cloud
    ct.export(real / "ball_ct.stl")
    cap = trimesh.sample.sample_surface(ct, 6000, seed=0)[0]
    np.save(real / "ball_us.npy", cap[cap[:, 2] > 0])
    res = subprocess.run([sys.executable, str(script), "--device", "cpu", "--quick", "--e1", "--out", str(out),
                          "--cache", str(tmp_path / "cache"), "--variant", "train.lr=0.004", "--real", str(real)],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads((out / "gpu_check.json").read_text())
    assert not [r for r in rows if r["stage"] == "error"], (out / "errors.txt").read_text()
    e2e = [r for r in rows if r["stage"] == "end to end"]
    assert [(r["preset"], r["variant"]) for r in e2e] == [
        ("robust", None), ("robust", "train.budget=cpu"), ("robust", "train.lr=0.004"), ("fast", None),
        ("official", None)]
    assert all(r["train_step"] == "eager" and r["budget"] in ("cpu", "reference") for r in e2e)
    timing = [r for r in rows if r["stage"] == "step timing"]
    assert [r["preset"] for r in timing] == ["robust", "fast", "official"]
    assert all(r["eager_ms"] > 0 and r["graph_ms"] > 0 for r in timing)
    many = next(r for r in rows if r["stage"] == "reconstruct_many")
    assert many["scans"] == 2 and many["many_s"] > 0
    assert [(r["case"], r["variant"]) for r in rows if r["stage"] == "real cloud"] == [
        ("ball", None), ("ball", "train.budget=cpu")]
    table = res.stdout
    assert "reference code ~340 s" in table and "reconstruct_many: 2 scans" in table
    results = (out / "e1" / "results.csv").read_text().splitlines()
    assert len(results) == 1 + 5                                     # one cell per method of Table 1
    assert "**CD (mm)**" in (out / "e1_report.md").read_text()


def test_the_ray_engine_gives_the_same_table_and_retries_a_killed_worker(dataset, tmp_path):
    """A local two-CPU Ray cluster on loopback: the worker running the first cell is killed
    (SIGKILL) once its folder appears; Ray starts the cell again and the table equals the local
    engine's."""
    ray = pytest.importorskip("ray")
    import subprocess
    import threading

    units = read_manifest(dataset)
    cells = plan(units, None, ["ultraboneudf"], [], QUICK, "fast", 0)
    local, remote = tmp_path / "local", tmp_path / "ray"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a Ray task of one CPU runs torch on one thread
    try:
        run_cells(cells, local, device="cpu", samples=5000)
    finally:
        torch.set_num_threads(threads)
    killed = []

    def kill_the_first_worker():
        deadline = time.time() + 120
        while time.time() < deadline and not killed:
            if (remote / "cells").exists() and any((remote / "cells").iterdir()):
                time.sleep(0.5)  # inside the cell's work
                killed.append(subprocess.run(["pkill", "-9", "-f", "ray::_run_cell"]).returncode == 0)
            time.sleep(0.05)

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             _node_ip_address="127.0.0.1")
    try:
        watcher = threading.Thread(target=kill_the_first_worker)
        watcher.start()
        counts = run_cells(cells, remote, device="cpu", samples=5000, engine="ray")
        watcher.join()
    finally:
        ray.shutdown()
    assert killed == [True]                                   # a worker died in the middle of a cell
    assert counts == {"done": 2, "skipped": 0, "failed": 0}   # and its cell was run again
    strip = lambda rows: [{k: v for k, v in r.items() if not k.endswith("_s")} for r in rows]  # noqa: E731
    assert strip(finished_rows(remote)) == strip(finished_rows(local))
    assert (remote / "results.csv").read_text().count("\n") == 3


def test_a_dataset_cloud_brings_its_probe_positions_and_frames(tmp_path):
    from ultraboneudf.bench.runner import _read_input

    rng = np.random.default_rng(0)
    points, probe = rng.uniform(0, 50, (300, 3)), rng.uniform(0, 50, (300, 3))
    frames = np.repeat(np.arange(3), 100)
    np.savez(tmp_path / "sweep.npz", points=points, probe=probe, frame=frames)
    np.savez(tmp_path / "older.npz", points=points, probe=probe)       # written before frames were kept
    got = _read_input(tmp_path / "sweep.npz")
    np.testing.assert_array_equal(got[0], points)
    np.testing.assert_array_equal(got[1], probe)
    np.testing.assert_array_equal(got[2], frames)
    assert _read_input(tmp_path / "older.npz")[2] is None
    from ultraboneudf.io import encode_points
    from ultraboneudf.sweep.compound import CompoundedPoints

    cp = CompoundedPoints(points=points, frame_index=frames, probe_position=probe,
                          beam_direction=np.tile([0.0, 0.0, -1.0], (300, 1)), pixel=np.zeros((300, 2)))
    (tmp_path / "cloud.ply").write_bytes(encode_points(tmp_path / "cloud.ply", cp))  # as sweep2points
    got = _read_input(tmp_path / "cloud.ply")
    np.testing.assert_array_equal(got[1], probe)
    np.testing.assert_array_equal(got[2], frames)


def test_cells_being_written_are_not_finished_and_ids_stay_in_their_folder(tmp_path, dataset):
    """A cell is staged under a hidden name and put in place whole: a staged one never counts as
    finished. A manifest id names a folder, so it must be a plain name: never ``../x`` or ``/x``."""
    staged = tmp_path / "run" / "cells" / ".ball__ultraboneudf__0.1-abcdef-00.ubtmp"
    staged.mkdir(parents=True)
    (staged / "result.json").write_text(json.dumps({"status": "ok"}))
    assert finished_rows(tmp_path / "run") == []
    text = dataset.read_text().splitlines()
    for uid in ("../../x", "/abs/x", "a/b", ".."):
        bad = dataset.parent / "bad.csv"
        bad.write_text(text[0] + "\n" + text[1].replace("ball,", f"{uid},", 1) + "\n")
        with pytest.raises(InputError, match=rf"line 2: id '{re.escape(uid)}' is not a plain name"):
            read_manifest(bad)
