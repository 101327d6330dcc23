"""`ultraboneudf demo` end to end (few iterations: the plumbing, not the accuracy)."""

import json

from PIL import Image

from ultraboneudf.cli import main
from ultraboneudf.synth import bone_phantom


def test_phantom_is_open_slice_structured_with_gaps():
    ph = bone_phantom(seed=0)
    assert 10_000 < len(ph.points) < 30_000
    frames = ph.frame
    assert len(frames) == len(ph.points) and len(set(frames)) > 100
    # two runs of missing frames: gaps in the frame index
    assert (frames.max() + 1) - len(set(frames)) >= 8
    assert ph.truth.is_watertight is False and ph.truth.area > 2_000


def test_demo_writes_everything(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--iters", "300", "--samples", "100000", "--quiet",
                 "--set", "train.batch=1000", "--set", "extract.max_depth=7"]) == 0
    printed = capsys.readouterr().out
    assert "Chamfer distance to the known truth" in printed
    for name in ("demo_points.xyz", "demo_truth.ply", "demo_mesh.ply", "demo_mesh.ply.json", "demo_eval.json",
                 "demo_mesh.png"):
        assert (out / name).stat().st_size > 0, name
    side = json.loads((out / "demo_mesh.ply.json").read_text())
    assert side["preset"] == "robust" and side["config"]["extract"]["mode"] == "clean"
    ev = json.loads((out / "demo_eval.json").read_text())
    assert ev["failed"] is False and 0 < ev["cd_mm"] < 5.0
    assert Image.open(out / "demo_mesh.png").size[0] > 400
