"""``ultraboneudf evaluate``, ``render`` and ``stats`` end to end (small sample counts)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from ultraboneudf.cli import main
from ultraboneudf.evaluation import JSON_KEYS, SHARE_KEYS, Record, write_results_csv


@pytest.fixture()
def files(tmp_path):
    gt = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    recon = trimesh.Trimesh(gt.vertices * 1.1, gt.faces, process=False)  # 1 mm larger
    gt.export(tmp_path / "gt.ply")
    recon.export(tmp_path / "recon.ply")
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    (tmp_path / "empty.ply").write_bytes(trimesh.exchange.ply.export_ply(empty))
    cap = gt.vertices[gt.vertices[:, 2] > 5.0]  # raw cloud: the top cap only
    np.savetxt(tmp_path / "raw.xyz", cap)
    return tmp_path


def test_evaluate_json_has_exactly_the_design_keys(files, capsys):
    out = files / "m.json"
    rc = main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--samples", "20000",
               "--json", str(out), "--quiet"])
    assert rc == 0
    data = json.loads(out.read_text())
    assert list(data) == list(JSON_KEYS)
    assert data["cd_mm"] == pytest.approx(1.0, abs=0.05) and data["samples"] == 20000
    assert data["pseudo_gt_mm"] is None
    out_text = capsys.readouterr().out
    assert "CD" in out_text
    # mesh quality of the 1.1× sphere: 1.21× the area, closed, one component, edge-manifold
    assert ("(1.210× the ground-truth mesh), 1 components, 0 boundary edges (0 loops), "
            "0 non-manifold edges, 0 duplicate faces") in out_text


def test_evaluate_with_pseudo_ground_truth(files):
    out = files / "m.json"
    assert main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--points",
                 str(files / "raw.xyz"), "--pseudo-gt-mm", "1", "--samples", "20000", "--json", str(out),
                 "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert data["pseudo_gt_mm"] == 1.0
    # d_GR only covers the scanned cap; d_RG still sees the whole reconstruction
    assert data["d_gr_mean_mm"] == pytest.approx(1.0, abs=0.1) and data["d_rg_mean_mm"] > 3.0


def test_evaluate_shares_within_a_distance(files, capsys):
    # the reconstruction lies 1 mm outside the ground truth everywhere: all of it within 1.5 mm,
    # none of it within 0.5 mm, in both directions
    for within, share in ((1.5, 1.0), (0.5, 0.0)):
        out = files / f"m{within}.json"
        assert main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--samples", "20000",
                     "--within-mm", str(within), "--json", str(out), "--quiet"]) == 0
        data = json.loads(out.read_text())
        assert list(data) == list(JSON_KEYS + SHARE_KEYS) and data["within_mm"] == within
        assert data["on_gt"] == share and data["covered"] == share
        assert f"within {within:g} mm: {share:.3f} of the mesh area" in capsys.readouterr().out
    # with the pseudo ground truth (the cap) the share on the ground truth is still the whole mesh's
    out = files / "p.json"
    assert main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--points",
                 str(files / "raw.xyz"), "--samples", "20000", "--within-mm", "1.5", "--json", str(out),
                 "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert data["on_gt"] == 1.0 and data["covered"] == 1.0 and data["d_rg_mean_mm"] > 3.0


def test_a_ground_truth_in_another_frame_is_said_and_placed_by_its_pose(files, capsys):
    # the CT as it came, 300 mm away and turned: the scores are meaningless, and a line says why
    turn = trimesh.transformations.rotation_matrix(0.4, [1, 2, 3])
    turn[:3, 3] = [300.0, 0.0, 0.0]
    ct = trimesh.load(files / "gt.ply")
    ct.apply_transform(np.linalg.inv(turn))
    ct.export(files / "ct.ply")
    args = ["evaluate", str(files / "recon.ply"), "--gt", str(files / "ct.ply"), "--samples", "20000", "--quiet"]
    assert main([*args, "--json", str(files / "far.json")]) == 0
    assert "recon.ply and" in capsys.readouterr().err
    assert json.loads((files / "far.json").read_text())["cd_mm"] > 100
    # placed by the pose (as `register` writes it), the same scores as against the CT in place
    (files / "T.json").write_text(json.dumps({"transform": turn.tolist()}))
    assert main([*args, "--gt-pose", str(files / "T.json"), "--json", str(files / "placed.json")]) == 0
    assert capsys.readouterr().err == ""
    assert main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--samples", "20000",
                 "--quiet", "--json", str(files / "inplace.json")]) == 0
    placed, inplace = (json.loads((files / n).read_text()) for n in ("placed.json", "inplace.json"))
    assert placed["cd_mm"] == pytest.approx(inplace["cd_mm"], abs=0.02)
    assert placed["cd_mm"] == pytest.approx(1.0, abs=0.1)
    # the file the pose came from is in the sidecar's inputs; the CT file is not touched
    assert str(files / "T.json") in json.loads((files / "placed.json.json").read_text())["inputs"]
    assert trimesh.load(files / "ct.ply").bounds[0][0] < -200


def test_a_ground_truth_in_metres_is_said(files, capsys):
    ct = trimesh.load(files / "gt.ply")
    ct.apply_scale(0.001)
    ct.export(files / "ct_m.ply")
    assert main(["evaluate", str(files / "recon.ply"), "--gt", str(files / "ct_m.ply"), "--samples", "2000",
                 "--quiet"]) == 0
    assert "are both in mm?" in capsys.readouterr().err


def test_evaluate_empty_mesh_is_a_counted_failure(files, capsys):
    out = files / "m.json"
    assert main(["evaluate", str(files / "empty.ply"), "--gt", str(files / "gt.ply"), "--samples", "1000",
                 "--json", str(out), "--quiet"]) == 0
    data = json.loads(out.read_text())
    assert list(data) == list(JSON_KEYS) and data["cd_mm"] is None and data["hd95_mm"] is None
    assert "counted as a failure" in capsys.readouterr().err


@pytest.mark.parametrize("args, message", [
    (["missing.ply", "--gt", "gt.ply"], "missing.ply: no such file"),
    (["recon.ply", "--gt", "empty.ply"], "empty.ply: holds no triangles"),
    (["recon.ply", "--gt", "gt.ply", "--pseudo-gt-mm", "1"], "--pseudo-gt-mm needs --points"),
    (["recon.ply", "--gt", "gt.ply", "--samples", "0"], "--samples"),
    (["recon.ply", "--gt", "gt.ply", "--within-mm", "-1"], "--within-mm: must be a finite number ≥ 0 mm"),
    (["recon.ply", "--gt", "gt.ply", "--within-mm", "nan"], "--within-mm: must be a finite number ≥ 0 mm"),
    (["recon.ply", "--gt", "gt.ply", "--gt-pose", "none.json"], "none.json: no such file"),
    (["recon.ply", "--gt", "gt.ply", "--gt-pose", "raw.xyz"], "raw.xyz"),
])
def test_evaluate_bad_input_exits_2_naming_the_problem(files, capsys, monkeypatch, args, message):
    monkeypatch.chdir(files)
    assert main(["evaluate", *args, "--json", "out.json"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (files / "out.json").exists()


def test_render_png_grid_and_html(files):
    png = files / "r.png"
    assert main(["render", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "-o", str(png),
                 "--tile-height", "160", "--colour-samples", "20000"]) == 0
    assert Image.open(png).size[1] == 160
    grid = files / "g.png"
    assert main(["render", str(files / "recon.ply"), str(files / "empty.ply"), "--gt", str(files / "gt.ply"),
                 "-o", str(grid), "--labels", "a,b", "--views", "front,30:20", "--tile-height", "100",
                 "--colour-samples", "20000", "--show-gt"]) == 0
    assert Image.open(grid).size[1] == 2 * 100 + int(54 * 0.75)
    page = files / "v.html"
    assert main(["render", str(files / "recon.ply"), "--gt", str(files / "gt.ply"), "--points",
                 str(files / "raw.xyz"), "-o", str(page), "--colour-samples", "20000"]) == 0
    assert "ready webgl2" in page.read_text()  # the status script is in the page
    assert main(["render", str(files / "recon.ply"), "-o", str(files / "x.jpg")]) == 2


def test_render_places_the_ground_truth_by_its_pose(files, capsys):
    shift = np.eye(4)
    shift[:3, 3] = [0.0, 250.0, 0.0]
    ct = trimesh.load(files / "gt.ply")
    ct.apply_translation([0.0, -250.0, 0.0])
    ct.export(files / "ct.ply")
    (files / "T.txt").write_text("\n".join(" ".join(str(v) for v in row) for row in shift))
    common = ["--tile-height", "120", "--colour-samples", "5000"]
    assert main(["render", str(files / "recon.ply"), "--gt", str(files / "ct.ply"), "-o", str(files / "far.png"),
                 *common]) == 0
    assert "do not overlap" in capsys.readouterr().err
    for name, extra in (("placed.png", ["--gt", str(files / "ct.ply"), "--gt-pose", str(files / "T.txt")]),
                        ("inplace.png", ["--gt", str(files / "gt.ply")])):
        assert main(["render", str(files / "recon.ply"), *extra, "-o", str(files / name), *common]) == 0
        assert "warning" not in capsys.readouterr().err
    # the same colours as against the ground truth in place: a 1 mm offset everywhere
    placed, inplace = (np.asarray(Image.open(files / n).convert("RGB"), dtype=float) for n in ("placed.png", "inplace.png"))
    assert np.abs(placed - inplace).mean() < 2.0
    assert main(["render", str(files / "recon.ply"), "--gt-pose", str(files / "T.txt"), "-o",
                 str(files / "x.png")]) == 2
    assert "--gt-pose places the ground truth and needs --gt" in capsys.readouterr().err


def test_stats_prints_tables_and_tests(files, capsys):
    rng = np.random.default_rng(0)
    recs = []
    for s in range(3):
        for r in range(4):
            base = 1.0 + 0.2 * s + rng.random() * 0.1
            recs.append(Record("ultraboneudf", f"#{s + 1}", f"r{r}", base, 3 * base))
            recs.append(Record("capudf", f"#{s + 1}", f"r{r}", base + 0.3 + 0.01 * r, 3 * base + 1 + 0.01 * r))
    write_results_csv(recs, files / "results.csv")
    assert main(["stats", str(files / "results.csv"), "--baseline", "ultraboneudf", "--k", "4"]) == 0
    out = capsys.readouterr().out
    assert "**CD (mm)**" in out and "**HD95 (mm)**" in out and "Bonferroni k = 4" in out
    assert "| capudf | 12 |" in out  # n = 12 paired reconstructions
    assert main(["stats", str(files / "results.csv"), "--baseline", "ultraboneudf", "--format", "latex",
                 "--metric", "cd_mm", "-o", str(files / "t.tex")]) == 0
    assert "\\textbf" in (files / "t.tex").read_text()
    assert main(["stats", str(files / "results.csv"), "--baseline", "nope"]) == 2
