"""Compounding mask pixels into world points, outlier removal, the one-call API and the CLI."""

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.errors import InputError
from ultraboneudf.io import load_points
from ultraboneudf.sweep import (
    Sweep,
    compound,
    points_from_sweep,
    local_outlier_mask,
    outlier_mask,
    statistical_outlier_mask,
    sweep_to_points,
    top_boundary,
    write_sweep,
)
from ultraboneudf.sweep.outliers import radius_outlier_mask
from ultraboneudf.sweep.transforms import rigid_from_euler


def plane_sweep(n=4, w=6, h=5):
    """Frames stacked along z (1 mm apart), image x → world x, image y (beam) → world y."""
    poses = np.stack([rigid_from_euler([0, 0, float(i)], [0, 0, 0]) for i in range(n)])
    masks = np.zeros((n, h, w), dtype=bool)
    return Sweep(image_to_world=poses, spacing_mm=0.5, image_size=(w, h), masks=masks, pixel_offset=0.5)


def test_compound_hand_computed():
    s = plane_sweep()
    s.masks[2, 3, 2] = True  # frame 2, row 3, column 2
    cp = compound(s)
    np.testing.assert_allclose(cp.points, [[1.25, 1.75, 2.0]])
    np.testing.assert_array_equal(cp.frame_index, [2])
    np.testing.assert_allclose(cp.probe_position, [[1.25, 0.0, 2.0]])
    np.testing.assert_allclose(cp.beam_direction, [[0.0, 1.0, 0.0]])
    np.testing.assert_allclose(cp.depth_mm, [1.75])
    np.testing.assert_allclose(cp.pixel, [[2, 3]])


def test_probe_plus_depth_along_beam_is_the_point():
    rng = np.random.default_rng(0)
    poses = np.stack([rigid_from_euler(rng.uniform(-50, 50, 3), rng.uniform(-90, 90, 3)) for _ in range(3)])
    masks = rng.random((3, 7, 9)) < 0.3
    s = Sweep(image_to_world=poses, spacing_mm=(0.3, 0.2), image_size=(9, 7), masks=masks)
    cp = compound(s)
    assert len(cp) == masks.sum()
    np.testing.assert_allclose(cp.probe_position + cp.depth_mm[:, None] * cp.beam_direction, cp.points,
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(cp.beam_direction, axis=1), 1.0)


def test_top_boundary():
    m = np.zeros((6, 4), dtype=bool)
    m[2:5, 1] = True
    m[[1, 4], 3] = True
    t = top_boundary(m)
    np.testing.assert_array_equal(np.argwhere(t), [[1, 3], [2, 1]])
    s = plane_sweep()
    s.masks[0] = False
    s.masks[0, 1:4, 0] = True
    assert len(compound(s, top_only=True)) == 1 and len(compound(s)) == 3


def test_outlier_removal():
    g = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), indexing="ij"), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))])
    pts = np.vstack([pts, [[10, 10, 30.0]]])
    keep = statistical_outlier_mask(pts, k=8, std_ratio=2.0)
    assert not keep[-1] and keep[:-1].all()
    keep_r = radius_outlier_mask(pts, radius_mm=1.5, min_neighbors=3)
    assert not keep_r[-1] and keep_r[:-1].all()


def test_local_rule_keeps_a_sparse_surface_and_drops_echoes_beside_a_dense_one():
    # a dense surface (0.25 mm) and, 5 mm beyond it, a face seen by a quarter of the beams
    # along each axis (1 mm): the local rule keeps both and drops three echoes 1.5-3 mm off the
    # dense surface; the statistical rule drops the sparse face with them
    g = np.stack(np.meshgrid(np.arange(0, 10, 0.25), np.arange(0, 10, 0.25), indexing="ij"), -1).reshape(-1, 2)
    dense = np.column_stack([g, np.zeros(len(g))])
    s, y = np.meshgrid(np.arange(0.0, 8.0), np.arange(0.0, 10.0), indexing="ij")
    sparse = np.column_stack([15 + s.ravel() * np.cos(1.2), y.ravel(), -s.ravel() * np.sin(1.2)])
    echoes = np.array([[5, 5, -2.0], [2, 7, -3.0], [7, 3, 1.5]])
    pts = np.vstack([dense, sparse, echoes])
    n_dense, n_surface = len(dense), len(dense) + len(sparse)
    local = local_outlier_mask(pts, k=16, factor=1.5)
    assert local[:n_surface].all() and not local[n_surface:].any()
    np.testing.assert_array_equal(outlier_mask(pts), local)
    statistical = outlier_mask(pts, "statistical", k=16, std_ratio=2.0)
    assert statistical[:n_dense].all() and not statistical[n_dense:].any()
    with pytest.raises(ValueError, match="unknown outlier rule"):
        outlier_mask(pts, "median")
    assert local_outlier_mask(pts[:10], k=16).all()  # too few points to judge


def test_sweep_to_points_and_points_from_sweep(tmp_path):
    s = plane_sweep(n=30, w=40, h=20)
    s.masks[:, 10, 5:35] = True  # a flat "bone" 5 mm deep
    s.masks[:, 12:15, 5:35] = True  # a thick band: top_only keeps row 10
    s.masks[7, 2, 20] = True  # a stray pixel on one frame (removed as an outlier)
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    cp = sweep_to_points(tmp_path / "sw")
    # top_only takes the stray pixel in its scan line; outlier removal then drops it
    assert len(cp) == 30 * 30 - 1
    np.testing.assert_allclose(cp.points[:, 1], 5.25)
    pts = points_from_sweep(tmp_path / "sw", top_only=False, remove_outliers=False,
                            remove_fragments=False)
    assert pts.shape == (30 * 30 * 4 + 1, 3) and pts.dtype == np.float64
    # the stray pixel is also a fragment that the neighbouring frames do not confirm
    assert len(points_from_sweep(tmp_path / "sw", top_only=False, remove_outliers=False)) == 30 * 30 * 4
    assert len(sweep_to_points(tmp_path / "sw", outlier_rule="statistical")) == 30 * 30 - 1
    with pytest.raises(InputError, match="unknown outlier rule"):
        sweep_to_points(tmp_path / "sw", outlier_rule="median")
    every3 = sweep_to_points(tmp_path / "sw", frame_step=3)
    assert set(np.unique(every3.frame_index)) == set(range(0, 30, 3))


def test_no_bone_found_is_an_input_error(tmp_path):
    s = plane_sweep()
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    with pytest.raises(InputError, match="no bone found"):
        points_from_sweep(tmp_path / "sw")


def test_masks_option_needs_images_or_masks():
    s = plane_sweep().replace(masks=None)
    with pytest.raises(InputError, match="no B-mode frames"):
        sweep_to_points(s, segment="classical")
    with pytest.raises(InputError, match="no bone masks"):
        sweep_to_points(s, segment="masks")
    with pytest.raises(InputError, match="unknown segmentation"):
        sweep_to_points(plane_sweep(), segment="magic")


@pytest.mark.parametrize("suffix", [".ply", ".npz", ".csv", ".xyz", ".npy"])
def test_cli_sweep2points_outputs(tmp_path, suffix, capsys):
    s = plane_sweep(n=20, w=30, h=16)
    s.masks[:, 8, 3:27] = True
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    out = tmp_path / f"pts{suffix}"
    assert main(["sweep2points", str(tmp_path / "sw"), "-o", str(out), "--quiet"]) == 0
    assert "480 points from 20/20 frames" in capsys.readouterr().out
    pts = load_points(out)
    assert pts.shape == (480, 3)
    np.testing.assert_allclose(pts[:, 1], 4.25, atol=1e-6)
    if suffix == ".npz":
        data = np.load(out)
        assert set(data.files) >= {"points", "frame_index", "probe_position", "beam_direction"}
    if suffix == ".ply":
        import trimesh

        ply = trimesh.load(out, process=False)
        frames = ply.metadata["_ply_raw"]["vertex"]["data"]["frame"]
        assert sorted(set(frames.tolist())) == list(range(20))


def test_cli_rejects_unknown_output_suffix(tmp_path, capsys):
    s = plane_sweep()
    s.masks[:, 1, 1] = True
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    code = main(["sweep2points", str(tmp_path / "sw"), "-o", str(tmp_path / "p.vtk"), "--quiet"])
    assert code == 2 and "p.vtk" in capsys.readouterr().err


def test_cli_sweep2points_outlier_options(tmp_path, capsys):
    s = plane_sweep(n=20, w=30, h=16)
    s.masks[:, 8, 3:27] = True
    s.masks[7, 2, 20] = True  # a stray pixel on one frame
    write_sweep(s.replace(images=None), tmp_path / "sw", write_images=False)
    out = tmp_path / "pts.npy"
    for rule in ("local", "statistical"):
        assert main(["sweep2points", str(tmp_path / "sw"), "-o", str(out), "--quiet",
                     "--outlier-rule", rule]) == 0
        assert load_points(out).shape == (479, 3)
    assert main(["sweep2points", str(tmp_path / "sw"), "-o", str(out), "--quiet", "--no-outliers"]) == 0
    assert load_points(out).shape == (480, 3)
    capsys.readouterr()
    code = main(["sweep2points", str(tmp_path / "sw"), "-o", str(out), "--quiet", "--outlier-factor", "1"])
    assert code == 2 and "--outlier-factor" in capsys.readouterr().err
