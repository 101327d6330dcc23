"""Frame-to-frame registration (sweep/align.py) on slice-structured samples of analytic surfaces
with known per-frame tracking errors, and through the command line on a simulated sweep."""

import numpy as np
import pytest
import trimesh

from ultraboneudf.cli import main
from ultraboneudf.sweep import CompoundedPoints, align_frames
from ultraboneudf.synth.simulator import config_with_noise, simulate_sweep

RADIUS = 15.0      # the bone: a cylinder of this radius along y (the sweep direction), top facing +z
PROBE_Z = 40.0     # the probe face, beams along −z


def slices(spacing=1.5, n_frames=41, beam_noise=0.0, offsets=None, false_echoes=0.0, seed=0):
    """Frames at y = spacing·i, each a line of points across x ∈ [−10, 10] mm on the cylinder,
    beams straight down; ``offsets`` (F,) move whole frames along the beam (tracking error);
    ``false_echoes``: that share of the points 2–8 mm under the surface."""
    rng = np.random.default_rng(seed)
    x = np.arange(-10.0, 10.0, 0.15)
    parts = []
    for i in range(n_frames):
        z = np.sqrt(RADIUS ** 2 - x ** 2) + rng.normal(0.0, beam_noise, len(x)) if beam_noise else \
            np.sqrt(RADIUS ** 2 - x ** 2)
        fake = rng.random(len(x)) < false_echoes
        z = np.where(fake, z - rng.uniform(2.0, 8.0, len(x)), z)
        if offsets is not None:
            z = z - offsets[i]                                   # + along the beam = deeper
        pts = np.column_stack([x, np.full_like(x, spacing * i), z])
        probe = np.column_stack([x, np.full_like(x, spacing * i), np.full_like(x, PROBE_Z)])
        parts.append(CompoundedPoints(pts, np.full(len(x), i, np.int64), probe,
                                      np.tile([0.0, 0.0, -1.0], (len(x), 1)),
                                      np.column_stack([np.arange(len(x)), np.zeros(len(x))]).astype(float)))
    return CompoundedPoints.concatenate(parts)


def frame_offsets(cp):
    """(F,) each frame's median height above the true cylinder."""
    r = np.hypot(cp.points[:, 0], cp.points[:, 2]) - RADIUS
    return np.array([np.median(r[cp.frame_index == f]) for f in np.unique(cp.frame_index)])


def test_tracking_offsets_are_reduced():
    rng = np.random.default_rng(1)
    offsets = rng.normal(0.0, 0.3, 41)
    cp = slices(beam_noise=0.5, offsets=offsets, false_echoes=0.03)
    before = frame_offsets(cp)
    out, report = align_frames(cp)
    after = frame_offsets(out)
    inner = slice(5, -5)  # the ends have neighbours on one side only
    err_before = np.abs(before[inner] - before[inner].mean()).mean()
    err_after = np.abs(after[inner] - after[inner].mean()).mean()
    assert err_after < 0.6 * err_before  # what is left: the mean error of the neighbours
    assert report.aligned >= 33 and report.residual_after_mm < report.residual_before_mm


def test_a_consistent_sweep_stays_put():
    cp = slices()
    out, report = align_frames(cp)
    assert report.max_shift_mm < 0.02 and report.max_angle_deg < 0.05
    assert np.abs(out.points - cp.points).max() < 0.05


def test_end_frames_and_isolated_frames_are_not_moved():
    rng = np.random.default_rng(2)
    cp = slices(offsets=rng.normal(0.0, 0.3, 41))
    out, _ = align_frames(cp)
    for f in (0, 40):
        rows = cp.frame_index == f
        assert np.array_equal(out.points[rows], cp.points[rows])
    sparse = slices(spacing=10.0, n_frames=8, offsets=rng.normal(0.0, 0.3, 8))
    out, report = align_frames(sparse)
    assert report.aligned == 0 and np.array_equal(out.points, sparse.points)
    assert "no frame" in report.summary()


def test_frames_move_rigidly_and_the_input_is_kept():
    rng = np.random.default_rng(3)
    cp = slices(beam_noise=0.3, offsets=rng.normal(0.0, 0.3, 41))
    copy = cp.points.copy(), cp.probe_position.copy()
    out, report = align_frames(cp)
    assert np.array_equal(cp.points, copy[0]) and np.array_equal(cp.probe_position, copy[1])
    assert report.aligned > 0
    # each point keeps its distance to its probe position and its place along its beam
    d_in = cp.points - cp.probe_position
    d_out = out.points - out.probe_position
    np.testing.assert_allclose(np.linalg.norm(d_out, axis=1), np.linalg.norm(d_in, axis=1), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(out.beam_direction, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", d_out, out.beam_direction),
                               np.einsum("ij,ij->i", d_in, cp.beam_direction), atol=1e-9)
    # within a frame, distances between points are unchanged
    rows = np.flatnonzero(cp.frame_index == 20)
    a, b = rows[:-1], rows[1:]
    np.testing.assert_allclose(np.linalg.norm(out.points[a] - out.points[b], axis=1),
                               np.linalg.norm(cp.points[a] - cp.points[b], axis=1), atol=1e-9)


def test_simulated_sweep_tracking_error_is_reduced():
    """The simulator's sweep of a capsule with its hard level's tracking error (0.3 mm / 0.3° per
    frame): the frames' error along the surface normal shrinks."""
    from ultraboneudf.sweep import sweep_to_points

    capsule = trimesh.creation.capsule(height=60.0, radius=10.0, count=[48, 48])
    cfg = config_with_noise("hard", width_px=128, height_px=160, spacing_mm=0.3, missing_runs=0,
                            pred_fp_fraction=0.0, seed=5)
    sim = simulate_sweep(capsule, cfg)
    cp = sweep_to_points(sim.sweep, segment="masks")
    true = sim.true_positions(cp.frame_index, cp.pixel)
    out, report = align_frames(cp)

    # the capsule's normal at each true point: away from the nearest point of its axis segment
    axis = np.column_stack([np.zeros((len(true), 2)), np.clip(true[:, 2], -30.0, 30.0)])
    normal = (true - axis) / np.linalg.norm(true - axis, axis=1, keepdims=True)

    def normal_error(points):
        e = np.einsum("ij,ij->i", points - true, normal)
        return np.abs(e - e.mean()).mean()

    assert report.aligned > 0.5 * report.frames
    assert normal_error(out.points) < 0.85 * normal_error(cp.points)


def test_cli_aligns_frames_unless_told_not_to(tmp_path, capsys):
    capsule = trimesh.creation.capsule(height=40.0, radius=8.0, count=[32, 32])
    mesh = tmp_path / "capsule.ply"
    capsule.export(mesh)
    sweep = tmp_path / "sw"
    assert main(["simulate", str(mesh), "-o", str(sweep), "--frames", "24", "--width-px", "96",
                 "--height-px", "120", "--spacing-mm", "0.3", "--seed", "1", "--quiet"]) == 0
    aligned, tracked = tmp_path / "a.xyz", tmp_path / "t.xyz"
    assert main(["sweep2points", str(sweep), "-o", str(aligned), "--segment", "masks"]) == 0
    assert "aligned to their neighbours" in capsys.readouterr().err
    assert main(["sweep2points", str(sweep), "-o", str(tracked), "--segment", "masks",
                 "--no-align-frames"]) == 0
    assert "aligned" not in capsys.readouterr().err
    a, t = np.loadtxt(aligned), np.loadtxt(tracked)
    assert a.shape == t.shape and len(a) > 100
    assert np.array_equal(a[:, 3], t[:, 3])                        # the same points, frame by frame
    assert 0.0 < np.abs(a[:, :3] - t[:, :3]).max() < 2.0
    cloud = tmp_path / "cloud.xyz"
    np.savetxt(cloud, np.random.default_rng(0).normal(size=(50, 3)) * 20)
    assert main(["reconstruct", str(cloud), "-o", str(tmp_path / "m.ply"), "--no-align-frames"]) == 2
    assert "--no-align-frames applies to tracked sweeps" in capsys.readouterr().err


@pytest.mark.parametrize("n", [0, 1])
def test_too_few_points_or_frames(n):
    cp = slices(n_frames=max(n, 1))
    if n == 0:
        cp = cp.subset(np.zeros(len(cp), dtype=bool))
    out, report = align_frames(cp)
    assert report.aligned == 0 and np.array_equal(out.points, cp.points)
    assert report.as_dict()["residual_before_mm"] is None  # JSON has no NaN
