"""The command line: exit codes, one-line errors, no partial outputs."""

import json
import subprocess
import sys

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.io import sidecar_path

SMALL = ["--iters", "300", "--set", "train.batch=1000", "--set", "extract.max_depth=7",
         "--set", "model.hidden=64,64,64", "--quiet"]


def _cloud(path, n=2000):
    rng = np.random.default_rng(0)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, n)
    np.savetxt(path, np.c_[20 * np.cos(theta), rng.uniform(0, 40, n), 20 * np.sin(theta)])
    return path


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ultraboneudf.cli", *map(str, args)],
                          capture_output=True, text=True)


def test_version_and_help():
    out = run_cli("--version")
    assert out.returncode == 0 and out.stdout.startswith("ultraboneudf ")
    for cmd in ("reconstruct", "demo"):
        out = run_cli(cmd, "--help")
        assert out.returncode == 0 and "--preset" in out.stdout


def test_reconstruct_writes_mesh_and_sidecar(tmp_path, capsys):
    src = _cloud(tmp_path / "in.xyz")
    before = src.read_bytes()
    assert main(["reconstruct", str(src), "-o", str(tmp_path / "out.ply"), "--preset", "fast", *SMALL]) == 0
    side = json.loads((tmp_path / "out.ply.json").read_text())
    # 300 steps stop short of the open edges: the self-check warns about the input the mesh misses,
    # even with --quiet, and only about what the sidecar's data_fit shows
    fit, err = side["data_fit"], capsys.readouterr().err.splitlines()
    assert fit["input_far_fraction"] > 0.01 and fit["mesh_far_area_fraction"] == 0.0
    assert len(err) == 1 and err[0].startswith("ultraboneudf reconstruct: warning: ")
    assert f"{100 * fit['input_far_fraction']:.1f}% of the input points" in err[0]
    assert side["counts"]["parameters"] == 64 * 5 + 64 * 66 * 2 + 66
    assert side["config"]["train"]["iters"] == 300 and side["preset"] == "fast"
    assert side["input"]["path"].endswith("in.xyz") and len(side["input"]["sha256"]) == 64
    assert src.read_bytes() == before                       # the input is never modified


@pytest.mark.parametrize("case,message", [
    ("missing", "no such file"), ("ext", "unknown point cloud extension"), ("line", "line 7"),
    ("nan", "NaN"), ("few", "only 50 points"), ("same", "identical"), ("line3d", "collinear"),
    ("outext", "unknown mesh extension"), ("set", "unknown config key"),
])
def test_bad_input_one_line_exit_2_no_output(tmp_path, case, message):
    src = tmp_path / "in.xyz"
    pts = np.random.default_rng(1).random((300, 3))
    out = tmp_path / "out.ply"
    extra = []
    if case == "missing":
        src = tmp_path / "nothing.xyz"
    elif case == "ext":
        src = tmp_path / "in.las"
        src.write_text("1 2 3\n")
    elif case == "line":
        lines = [f"{a} {b} {c}" for a, b, c in pts]
        lines[6] = "1 2 x"
        src.write_text("\n".join(lines))
    elif case == "nan":
        pts[10, 0] = np.nan
        np.savetxt(src, pts)
    elif case == "few":
        np.savetxt(src, pts[:50])
    elif case == "same":
        np.savetxt(src, np.ones((300, 3)))
    elif case == "line3d":
        np.savetxt(src, np.linspace(0, 1, 300)[:, None] * [1, 2, 3])
    elif case == "outext":
        np.savetxt(src, pts)
        out = tmp_path / "out.vtk"
    elif case == "set":
        np.savetxt(src, pts)
        extra = ["--set", "train.bogus=1"]
    res = run_cli("reconstruct", src, "-o", out, "--quiet", *extra)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in res.stderr
    if case != "missing":
        assert str(src.name) in lines[0] or case in ("outext", "set")
    assert not out.exists() and not sidecar_path(out).exists()


def test_usage_error_exit_2():
    assert run_cli("reconstruct").returncode == 2
    assert run_cli("bogus-command").returncode == 2


@pytest.mark.parametrize("extra,message", [
    (["--seed", "-1"], "argument --seed: -1 is below 0"),
    (["--iters", "0"], "argument --iters: 0 is below 1"),
    (["--device", "tpu"], "unknown device 'tpu'"),
    (["--set", "extract.max_depth=30"], "extract.max_depth=30 (between 1 and 11)"),
    (["--set", "train.lr=-1"], "train.lr=-1.0 (a learning rate in (0, 1])"),
    (["--set", "extract.trim_mm=-1"], "extract.trim_mm=-1.0 (finite and 0 or more)"),
    (["--set", "train.lr=1e30"], "train.lr=1e+30 (a learning rate in (0, 1])"),
    (["--set", "loss.os_rows=-5"], "loss.os_rows=-5 (0 (all) or more)"),
    (["--set", "loss.gs_form=pairs"], "unknown loss.gs_form 'pairs'; choose one of per_anchor, broadcast"),
])
def test_out_of_range_options_are_one_line_exit_2(tmp_path, extra, message):
    src = _cloud(tmp_path / "in.xyz")
    res = run_cli("reconstruct", src, "-o", tmp_path / "out.ply", "--preset", "fast", "--quiet", *extra)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[-1] and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "out.ply").exists()


def test_help_and_usage_errors_load_neither_torch_nor_the_geometry_stack():
    """``--help``, ``--version`` and argument errors answer before PyTorch, trimesh or SciPy load
    (benchmarks/bench_cli.py times them)."""
    code = ("import sys\nfrom ultraboneudf.cli import main\n"
            "for argv in (['--help'], ['reconstruct', '--help'], ['simulate', '--help'], ['--version'],"
            " ['reconstruct', 'x.xyz', '-o', 'y.ply', '--seed', '-1']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            "heavy = sorted(m for m in ('torch', 'trimesh', 'scipy') if m in sys.modules)\n"
            "print('HEAVY', heavy, file=sys.stderr)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert "HEAVY []" in res.stderr, res.stderr[-500:]


def test_the_command_line_lists_every_registered_method():
    from ultraboneudf.methods import METHODS, NAMES

    assert tuple(METHODS) == NAMES


def test_info_reports_versions_devices_extras_and_data():
    res = run_cli("info", "--json")
    assert res.returncode == 0, res.stderr
    info = json.loads(res.stdout)
    import torch

    import ultraboneudf
    assert info["ultraboneudf"] == ultraboneudf.__version__
    assert info["packages"]["torch"] == torch.__version__
    assert info["cuda_available"] == torch.cuda.is_available()
    assert set(info["extras"]) == {"pymeshlab", "open3d", "onnxruntime"}
    assert set(info["shared_data"]) == {"bones", "ultrabones100k_sample", "plus"}
    text = run_cli("info")
    assert text.returncode == 0 and "CUDA available" in text.stdout
