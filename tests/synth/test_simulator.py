"""The sweep simulator on a capsule (a bone-like closed surface with a closed-form distance)."""

import json

import numpy as np
import pytest
import trimesh

from ultraboneudf.cli import main
from ultraboneudf.sweep import BoneDetector, compound, read_sweep, sweep_to_points
from ultraboneudf.synth.simulator import SimulationConfig, config_with_noise, simulate_sweep
from ultraboneudf.synth.scoring import mask_precision_recall, point_to_mesh_distance, surface_coverage

RADIUS, HALF = 8.0, 20.0  # capsule: segment z ∈ [−20, 20], radius 8 mm


def capsule_distance(p):
    z = np.clip(p[:, 2], -HALF, HALF)
    axis = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    return np.abs(np.linalg.norm(p - axis, axis=1) - RADIUS)


def small(noise="default", **kw):
    base = dict(width_px=128, height_px=160, spacing_mm=0.3, frame_spacing_mm=1.5, seed=3)
    base.update(kw)
    return config_with_noise(noise, **base)


@pytest.fixture(scope="module")
def capsule():
    return trimesh.creation.capsule(height=2 * HALF, radius=RADIUS, count=[48, 48])


@pytest.fixture(scope="module")
def sim(capsule):
    return simulate_sweep(capsule, small())


def test_shapes_and_path(sim):
    s = sim.sweep
    assert s.images.shape == (s.n_frames, 160, 128) and s.images.dtype == np.uint8
    assert sim.true_masks.shape == sim.pred_masks.shape == s.images.shape
    assert 25 <= s.n_frames <= 40
    normals = sim.true_image_to_world[:, :3, 2]
    assert np.abs(normals[:, 2]).min() > np.cos(np.deg2rad(15))   # frames ⟂ the long axis, ± tilt
    assert np.all(np.diff(sim.true_image_to_world[:, 2, 3] * np.sign(normals[0, 2])) > 0)  # forward


def test_true_masks_lie_on_the_surface(sim):
    cp = compound(sim.true_sweep())
    assert len(cp) > 1000
    d = capsule_distance(cp.points)
    assert d.max() <= 0.5 * sim.config.spacing_mm + 0.05   # floor(depth / s): half a pixel
    # one pixel per scan line, and only where the beam meets the bone
    assert sim.true_masks.sum(axis=1).max() == 1


def test_visible_truth(sim, capsule):
    vis = sim.visible_mesh
    assert 0 < vis.area < 0.6 * capsule.area
    up = -sim.true_image_to_world[:, :3, 1].mean(axis=0)
    facing = vis.face_normals @ (up / np.linalg.norm(up))
    assert np.average(facing > np.cos(np.deg2rad(80)), weights=vis.area_faces) > 0.95
    cp = compound(sim.true_sweep())
    assert surface_coverage(vis, cp.points, radius_mm=1.0) > 0.9


def test_visible_truth_does_not_depend_on_the_tessellation(capsule):
    # The same capsule with faces half as large: the visible surface is the same surface, so its
    # area and its connectedness must not change (beams coarser than the faces would miss faces of
    # the steep sides and leave islands).
    cfg = small()
    coarse = simulate_sweep(capsule, cfg).visible_mesh
    fine = simulate_sweep(capsule.subdivide(), cfg).visible_mesh
    assert fine.area == pytest.approx(coarse.area, rel=0.01)
    assert len(fine.split(only_watertight=False)) == 1


def test_tracking_noise_is_small_and_present(sim):
    true, rec = sim.true_image_to_world, sim.sweep.image_to_world
    shift = np.linalg.norm(true[:, :3, 3] - rec[:, :3, 3], axis=1)
    assert 0 < np.median(shift) < 1.5
    cos = (np.einsum("fij,fij->f", true[:, :3, :3], rec[:, :3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 1.0


def test_true_positions_undo_the_tracking_error(sim, capsule):
    cp = compound(sim.sweep, top_only=True)
    true = sim.true_positions(cp.frame_index, cp.pixel)
    shift = np.linalg.norm(cp.points - true, axis=1)
    assert 0 < np.median(shift) < 1.5                     # the recorded poses are off
    exact = simulate_sweep(capsule, small("none", n_frames=8))
    cp = compound(exact.sweep, top_only=True)
    np.testing.assert_allclose(exact.true_positions(cp.frame_index, cp.pixel), cp.points, atol=1e-9)


def test_bmode_has_bright_echo_and_shadow(sim):
    k = sim.sweep.n_frames // 2
    img = sim.sweep.images[k].astype(float)
    depth = sim.surface_depth_mm[k]
    cols = np.flatnonzero(np.isfinite(depth))
    rows = (depth[cols] / sim.config.spacing_mm).astype(int)
    echo = img[rows, cols].mean()
    below = np.mean([img[r + 10:r + 40, c].mean() for r, c in zip(rows, cols) if r + 40 < img.shape[0]])
    tissue = img[20:120, np.flatnonzero(~np.isfinite(depth))].mean()
    assert echo > 1.6 * tissue and below < 0.4 * tissue


def test_predicted_masks_have_errors_but_follow_the_bone(sim):
    p, r = mask_precision_recall(sim.pred_masks, sim.true_masks, sim.config.spacing_mm, 1.0)
    assert 0.6 < r < 1.0 and p > 0.6
    assert (sim.pred_masks & ~sim.true_masks).any()


def test_no_noise_preset(capsule):
    sim = simulate_sweep(capsule, small("none", n_frames=8))
    np.testing.assert_array_equal(sim.sweep.image_to_world, sim.true_image_to_world)
    from ultraboneudf.sweep import top_boundary

    top = np.stack([top_boundary(m) for m in sim.pred_masks])
    np.testing.assert_array_equal(top, sim.true_masks)


def test_deterministic(capsule):
    a = simulate_sweep(capsule, small(n_frames=4))
    b = simulate_sweep(capsule, small(n_frames=4))
    np.testing.assert_array_equal(a.sweep.images, b.sweep.images)
    np.testing.assert_array_equal(a.sweep.image_to_world, b.sweep.image_to_world)
    c = simulate_sweep(capsule, small(n_frames=4, seed=4))
    assert not np.array_equal(a.sweep.images, c.sweep.images)


def test_classical_detector_on_simulated_frames(sim):
    pred = BoneDetector().segment_stack(sim.sweep.images, sim.sweep.spacing_mm)
    p, r = mask_precision_recall(pred, sim.true_masks, sim.config.spacing_mm, 0.5)
    assert p > 0.9 and r > 0.85


def test_pipeline_accuracy_on_simulated_sweep(sim, capsule):
    cp = sweep_to_points(sim.sweep, segment="classical")
    d = capsule_distance(cp.points)
    assert np.median(d) < 0.5
    np.testing.assert_allclose(point_to_mesh_distance(cp.points[:500], capsule),
                               d[:500], atol=0.05)   # the mesh is a polygonal capsule
    assert surface_coverage(sim.visible_mesh, cp.points, 1.0) > 0.8


def test_write_and_read_back(sim, tmp_path):
    out = sim.write(tmp_path / "sim")
    for name in ("poses.csv", "calibration.json", "gt_visible.ply", "gt_closed.ply",
                 "simulation.json", "README.md", "truth/poses.csv"):
        assert (out / name).is_file(), name
    r = read_sweep(out)
    np.testing.assert_allclose(r.pixel_to_world(), sim.sweep.pixel_to_world(), atol=1e-9)
    np.testing.assert_array_equal(r.images, sim.sweep.images)
    np.testing.assert_array_equal(r.masks, sim.pred_masks)
    np.testing.assert_array_equal(read_sweep(out, mask_dir="masks_true").masks, sim.true_masks)
    t = read_sweep(out / "truth", masks=out / "masks_true", load_images=False)
    np.testing.assert_allclose(t.pixel_to_world(), sim.true_sweep().pixel_to_world(), atol=1e-9)
    vis = trimesh.load(out / "gt_visible.ply")
    assert len(vis.faces) == len(sim.visible_mesh.faces)
    meta = json.loads((out / "simulation.json").read_text())
    assert meta["config"]["seed"] == 3 and meta["info"]["frames"] == sim.sweep.n_frames


def test_cli_simulate_then_sweep2points(capsule, tmp_path, capsys):
    mesh_path = tmp_path / "capsule.ply"
    capsule.export(mesh_path)
    out = tmp_path / "sw"
    args = ["simulate", str(mesh_path), "-o", str(out), "--frames", "6", "--width-px", "96",
            "--height-px", "120", "--spacing-mm", "0.3", "--seed", "1", "--quiet"]
    assert main(args) == 0
    assert "6 frames" in capsys.readouterr().out
    assert main(args + ["--seed", "2"]) == 0     # an earlier simulation is replaced as a whole
    (out / "notes.txt").write_text("mine")
    assert main(args) == 2                       # a folder with a file of the user's is not
    assert "notes.txt" in capsys.readouterr().err and (out / "notes.txt").read_text() == "mine"
    (out / "notes.txt").unlink()
    pts = tmp_path / "p.xyz"
    assert main(["sweep2points", str(out), "-o", str(pts), "--segment", "classical", "--quiet"]) == 0
    assert np.median(capsule_distance(np.loadtxt(pts)[:, :3])) < 0.5


def test_cli_simulate_rejects_open_mesh(tmp_path, capsys):
    open_mesh = trimesh.creation.box()
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) > 0)
    path = tmp_path / "open.ply"
    open_mesh.export(path)
    assert main(["simulate", str(path), "-o", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "open.ply" in err and "not closed" in err
    assert not (tmp_path / "o").exists()


def test_unknown_options_rejected():
    from ultraboneudf.errors import InputError

    with pytest.raises(InputError, match="unknown noise"):
        config_with_noise("extreme")
    with pytest.raises(InputError, match="unknown simulation option"):
        config_with_noise("default", wobble=3)
    assert SimulationConfig().tracking_noise_mm > 0


def test_hard_level_knobs_noise_false_echoes_and_missing_frames(capsule):
    """``pred_beam_noise_mm`` scatters the predicted surface along the beam, ``pred_fp_fraction``
    moves that fraction of the scan lines into the shadow (up to ``pred_fp_depth_mm`` deeper),
    ``missing_runs`` drops runs of ``missing_run_mm`` of frames (the visible truth still covers them)."""
    base = dict(pred_gap_fraction=0.0, pred_fp_per_frame=0.0, pred_jitter_px=0.0, pred_bias_px=0.0,
                pred_thickness_px=1, n_frames=None, frame_spacing_mm=1.0)
    clean = simulate_sweep(capsule, small("none", **base))
    noisy = simulate_sweep(capsule, small("none", **base, pred_beam_noise_mm=0.9))
    echo = simulate_sweep(capsule, small("none", **base, pred_fp_fraction=0.2, pred_fp_depth_mm=6.0))
    d_clean = capsule_distance(compound(clean.sweep).points)
    d_noisy = capsule_distance(compound(noisy.sweep).points)
    assert np.median(d_clean) < 0.2
    assert 0.4 < np.median(d_noisy) < 0.8       # |N(0, 0.9)| has median 0.61, rounded to 0.3 mm pixels
    d_echo = capsule_distance(compound(echo.sweep).points)
    far = (d_echo > 0.5).mean()
    assert 0.12 < far < 0.2                      # 20% moved U(0, 6) mm: ~ 18% more than 0.5 mm
    assert d_echo.max() < 6.0 + 0.5
    gappy = simulate_sweep(capsule, small("none", **base, missing_runs=2, missing_run_mm=5.0))
    assert gappy.info["missing_frames"] >= 6 and gappy.sweep.n_frames == clean.sweep.n_frames - gappy.info["missing_frames"]
    along = gappy.true_image_to_world[:, 2, 3] * np.sign(gappy.true_image_to_world[0, 2, 2])
    assert np.diff(np.sort(along)).max() > 4.0   # a hole of ≥ 4 mm between recorded frames
    assert gappy.visible_mesh.area == pytest.approx(clean.visible_mesh.area, rel=1e-9)
    assert gappy.true_masks.shape[0] == gappy.sweep.n_frames


def test_robustness_levels_exist():
    hard = config_with_noise("hard")
    assert (hard.pred_beam_noise_mm, hard.pred_fp_fraction, hard.frame_spacing_mm) == (0.8, 0.03, 1.5)
    assert hard.missing_runs == 3 and hard.tracking_noise_mm == hard.tracking_noise_deg == 0.3
    assert config_with_noise("moderate").pred_beam_noise_mm == 0.3


def test_simulate_set_values_take_the_options_own_types(tmp_path, capsys):
    from ultraboneudf.cli import main
    from ultraboneudf.cli.cmd_simulate import parse_assignments

    assert parse_assignments(["n_frames=none", "sweep_axis=1,0,0", "missing_runs=2", "tilt_deg=3"]) == \
        {"n_frames": None, "sweep_axis": (1.0, 0.0, 0.0), "missing_runs": 2, "tilt_deg": 3.0}
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(radius=10).export(mesh)
    for item, words in (("seed=1.5", "'seed' (expected an integer)"), ("bogus=1", "unknown simulator option 'bogus'"),
                        ("width_px", "expected KEY=VALUE")):
        assert main(["simulate", str(mesh), "-o", str(tmp_path / "out"), "--set", item]) == 2
        err = capsys.readouterr().err
        assert words in err and len(err.strip().splitlines()) == 1


def test_real_level_adds_sheets_in_front_streaks_and_clusters_under_the_bone(capsule):
    """The ``real`` level's clutter (``pred_sheets_per_cm``, ``pred_streaks_per_frame``,
    ``pred_below_per_cm``) puts persistent false echoes outside the capsule (in front of the bone)
    and inside it (under the bone), from a random stream of its own: the masks of the bone itself
    are the same pixels with and without it."""
    base = dict(pred_gap_fraction=0.0, pred_fp_per_frame=0.0, pred_jitter_px=0.0, pred_bias_px=0.0,
                pred_thickness_px=1, n_frames=None, frame_spacing_mm=1.0, n_fascia=0)
    clean = simulate_sweep(capsule, small("none", **base))
    busy = simulate_sweep(capsule, small("none", **base, pred_sheets_per_cm=2.0, pred_streaks_per_frame=1.0,
                                         pred_below_per_cm=2.0))
    assert (busy.pred_masks >= clean.pred_masks).all()        # only added: the bone's pixels are unchanged
    added = busy.pred_masks & ~clean.pred_masks
    sim = busy.sweep.with_masks(added)
    pts = compound(sim, top_only=False).points
    r = np.linalg.norm(pts[:, :2], axis=1)
    inside = (r < RADIUS - 1.5) & (np.abs(pts[:, 2]) < HALF)
    outside = capsule_distance(pts) > 2.5
    assert (outside & ~inside).mean() > 0.5                  # sheets and streaks toward the probe
    assert inside.sum() > 100                                # reverberation clusters under the surface
    # sheets persist over neighbouring frames: the frames with added echoes come in runs
    frames = np.flatnonzero(added.any(axis=(1, 2)))
    assert len(frames) > 5 and np.mean(np.diff(frames) == 1) > 0.5


def test_real_level_offsets_the_boundary_slowly_along_the_sweep(capsule):
    base = dict(pred_gap_fraction=0.0, pred_fp_per_frame=0.0, pred_jitter_px=0.0, pred_bias_px=0.0,
                pred_thickness_px=1, n_frames=None, frame_spacing_mm=1.0)
    shifted = simulate_sweep(capsule, small("none", **base, pred_offset_mm=1.0))
    cp = compound(shifted.sweep)
    d = capsule_distance(cp.points)
    per_frame = np.array([np.median(d[cp.frame_index == f]) for f in np.unique(cp.frame_index)])
    assert 0.4 < np.median(per_frame) < 1.6                 # about a millimetre off the surface
    assert np.abs(np.diff(per_frame)).max() < 0.6            # drifting, not jumping, frame to frame
    assert config_with_noise("real").pred_offset_mm == 1.0


def test_real_level_moves_oblique_faces_out_of_the_bone(capsule):
    """``pred_oblique_mm`` moves each face's predicted boundary out of the bone along its normal by
    about ``pred_oblique_mm × (1 − cos incidence)``: faces square to the beam stay where they were,
    faces at 55–75° move out, as the steep faces of real clouds lie out of their CT. Each scan line
    is compared with itself without the offset (same frame, same column)."""
    base = dict(pred_gap_fraction=0.0, pred_fp_per_frame=0.0, pred_jitter_px=0.0, pred_bias_px=0.0,
                pred_thickness_px=1, n_frames=None, frame_spacing_mm=1.0, n_fascia=0)
    lines = {}
    for amount in (0.0, 1.5):
        cp = compound(simulate_sweep(capsule, small("none", **base, pred_oblique_mm=amount)).sweep)
        side = np.abs(cp.points[:, 2]) < HALF - 2.0          # the cylinder: its normal is radial
        for f, c, p, b in zip(cp.frame_index[side], cp.pixel[side, 0], cp.points[side], cp.beam_direction[side]):
            lines.setdefault((int(f), float(c)), {})[amount] = (p, b)
    pairs = [v for v in lines.values() if len(v) == 2]
    p0 = np.array([v[0.0][0] for v in pairs])
    p1 = np.array([v[1.5][0] for v in pairs])
    beam = np.array([v[0.0][1] for v in pairs])
    normal = np.column_stack([p0[:, :2], np.zeros(len(p0))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    angle = np.arccos(np.abs(np.einsum("ij,ij->i", normal, beam)))
    moved = np.einsum("ij,ij->i", p1 - p0, normal)           # mm out of the bone along its normal
    flat, steep = angle < np.radians(20), (angle > np.radians(55)) & (angle < np.radians(75))
    assert flat.sum() > 100 and steep.sum() > 100
    assert abs(np.median(moved[flat])) < 0.1                   # square faces unchanged
    expected = 1.5 * (1.0 - np.cos(angle[steep]))              # 0.6–1.1 mm
    assert np.median(moved[steep]) > 0.4
    assert np.median(np.abs(moved[steep] - expected)) < 0.15
    assert config_with_noise("real").pred_oblique_mm == 1.5
    assert config_with_noise("hard").pred_oblique_mm == 0.0


@pytest.mark.parametrize("field,bad", [
    ("n_frames", -3), ("n_frames", 1), ("width_px", 0), ("height_px", 10_000), ("spacing_mm", 0.0),
    ("frame_spacing_mm", -1.0), ("tilt_deg", 95.0), ("max_incidence_deg", 0.0), ("pred_gap_fraction", 1.5),
    ("shadow_level", -0.1), ("pred_thickness_px", 0), ("missing_runs", -1), ("sweep_axis", (0.0, 0.0, 0.0)),
    ("speed_variation", float("nan")), ("seed", -1), ("gt_step_mm", 0.0), ("pred_sheets_per_cm", -1.0)])
def test_impossible_settings_are_refused_naming_the_field(field, bad):
    """A setting no simulation can use is refused when the configuration is made, before any work
    (``n_frames=-3`` used to give a sweep of two frames)."""
    from ultraboneudf.errors import InputError

    with pytest.raises(InputError, match=rf"impossible simulator settings: {field}="):
        config_with_noise("default", **{field: bad})
