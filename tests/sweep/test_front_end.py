"""The sweep front end as a library stage: ``sweep_points(path, SweepOptions)``, the one flow the
command line runs."""

import json

import numpy as np
import pytest
import trimesh

import ultraboneudf
from ultraboneudf.cli import build_parser, main
from ultraboneudf.errors import InputError
from ultraboneudf.sweep.front_end import SweepOptions, SweepPoints, sweep_points


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A simulated tracked sweep of a capsule (24 frames, with bone masks and B-mode frames)."""
    tmp = tmp_path_factory.mktemp("front_end")
    mesh = tmp / "capsule.ply"
    trimesh.creation.capsule(height=40.0, radius=8.0, count=[32, 32]).export(mesh)
    folder = tmp / "sw"
    assert main(["simulate", str(mesh), "-o", str(folder), "--frames", "24", "--width-px", "96",
                 "--height-px", "120", "--spacing-mm", "0.3", "--seed", "1", "--quiet"]) == 0
    return folder


def test_options_round_trip_through_a_dict_and_the_command_line(tmp_path):
    opts = SweepOptions(calibration=tmp_path / "cal.xml", transforms=[tmp_path / "t.seq.mha"], segment="classical",
                        detector={"high": 0.4}, threshold=0.3, confirm_echoes=False, top_only=False,
                        remove_outliers=False, outlier_rule="statistical", outlier_k=8, outlier_std=2.5,
                        outlier_factor=1.8, drop_fragments=False, align_frames=False, frame_step=2)
    assert SweepOptions.from_dict(json.loads(json.dumps(opts.to_dict()))) == opts
    assert SweepOptions.from_dict(SweepOptions().to_dict()) == SweepOptions()
    with pytest.raises(InputError, match="unknown sweep option"):
        SweepOptions.from_dict({"segmnet": "masks"})
    with pytest.raises(InputError, match="unknown outlier rule"):
        SweepOptions(outlier_rule="median")
    with pytest.raises(Exception):
        opts.segment = "masks"  # frozen
    # the command line only translates its flags
    from ultraboneudf.cli.cmd_sweep2points import front_end_options

    args = build_parser().parse_args([
        "sweep2points", "sweep", "-o", "o.npz", "--calibration", str(tmp_path / "cal.xml"), "--transforms",
        str(tmp_path / "t.seq.mha"), "--segment", "classical", "--detector", "high=0.4", "--threshold", "0.3",
        "--no-consistency", "--all-pixels", "--no-outliers", "--outlier-rule", "statistical", "--outlier-k", "8",
        "--outlier-std", "2.5", "--outlier-factor", "1.8", "--no-align-frames", "--frame-step", "2"])
    assert front_end_options(args) == opts
    defaults = build_parser().parse_args(["sweep2points", "sweep", "-o", "o.npz"])
    assert front_end_options(defaults) == SweepOptions()


def test_sweep_points_gives_the_points_the_command_line_writes(sweep, tmp_path, capsys):
    for flags, options in (([], SweepOptions()),
                           (["--frame-step", "2", "--no-align-frames", "--no-consistency"],
                            SweepOptions(frame_step=2, align_frames=False, confirm_echoes=False,
                                         drop_fragments=False))):
        out = tmp_path / f"points{len(flags)}.npz"
        assert main(["sweep2points", str(sweep), "-o", str(out), "--quiet", *flags]) == 0
        sp = ultraboneudf.sweep_points(sweep, options)
        assert isinstance(sp, SweepPoints) and sp.segmentation == "masks"
        with np.load(out) as written:
            np.testing.assert_array_equal(written["points"], sp.points)
            np.testing.assert_array_equal(written["probe_position"], sp.probe_position)
            np.testing.assert_array_equal(written["frame_index"], sp.frame_index)
        assert sp.points.shape == (len(sp), 3) and len(sp) > 100
        assert set(sp.frame_index.tolist()) <= set(range(0, 24, options.frame_step))
        side = json.loads(out.with_name(out.name + ".json").read_text())
        assert side["sweep"]["points"]["count"] == len(sp) == sp.info["points"]["count"]
        assert ("alignment" in sp.info) == options.align_frames
        assert sp.dropped["fragments"] == (sp.info["fragments"] or {}).get("removed", 0)
        assert sp.dropped["outliers"] >= 0 and (options.drop_fragments or sp.dropped["fragments"] == 0)
    capsys.readouterr()


def test_what_is_dropped_is_counted(sweep):
    """Without the cleaning steps the front end keeps every compounded point; with them the counts
    dropped are the difference."""
    raw = sweep_points(sweep, SweepOptions(remove_outliers=False, drop_fragments=False, align_frames=False))
    assert raw.dropped == {"outliers": 0, "fragments": 0}
    clean = sweep_points(sweep, SweepOptions(align_frames=False))
    assert len(raw) - len(clean) == clean.dropped["outliers"] + clean.dropped["fragments"]
    # the points kept are points of the raw cloud, untouched (no registration here)
    kept = {tuple(p) for p in raw.points}
    assert all(tuple(p) in kept for p in clean.points)


def test_a_sweep_in_memory_takes_no_reading_options(sweep):
    from ultraboneudf.sweep import read_sweep

    sw = read_sweep(sweep)
    np.testing.assert_array_equal(sweep_points(sw).points, sweep_points(sweep).points)
    with pytest.raises(TypeError, match="mask_dir"):
        sweep_points(sw, SweepOptions(mask_dir="masks"))


def test_frames_that_are_a_bone_map(sweep, tmp_path, capsys):
    """A sequence whose frames are already a bone map (a bone enhancer's output: dark but for the
    bone) is refused by the classical detector with the way out in the message, and segmented by
    ``--segment probability``: the same points as the sweep's own masks give."""
    import dataclasses

    from ultraboneudf.cli.sweep_input import SEGMENT_NAMES
    from ultraboneudf.sweep import read_sweep, write_sweep
    from ultraboneudf.sweep.points import SEGMENT_CHOICES

    assert SEGMENT_NAMES == SEGMENT_CHOICES  # the command line's copy, kept to start without the sweep package

    sw = read_sweep(sweep)
    enhanced = dataclasses.replace(sw, images=np.where(sw.masks, 230, 0).astype(np.uint8), masks=None)
    path = write_sweep(enhanced, tmp_path / "enhanced.mha")
    out = tmp_path / "points.npz"
    assert main(["sweep2points", str(path), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no bone found" in err and "give --segment probability" in err and len(err.splitlines()) == 1
    assert not out.exists()

    assert main(["sweep2points", str(path), "--segment", "probability", "-o", str(out), "--quiet"]) == 0
    options = SweepOptions(align_frames=False)
    by_masks = sweep_points(sweep, options)
    by_map = sweep_points(path, dataclasses.replace(options, segment="probability"))
    assert by_map.segmentation == "probability" and len(by_map) > 100
    np.testing.assert_allclose(by_map.points, by_masks.points, atol=1e-6)
    with np.load(out) as written:
        assert len(written["points"]) == len(sweep_points(path, SweepOptions(segment="probability")))
    # a threshold above the map's brightness (230 of 255) finds nothing; one outside (0, 1] is refused
    assert main(["sweep2points", str(path), "--segment", "probability", "--threshold", "0.95",
                 "-o", str(tmp_path / "none.npz"), "--quiet"]) == 2
    assert "no bone found" in capsys.readouterr().err
    with pytest.raises(InputError, match="threshold"):
        sweep_points(path, SweepOptions(segment="probability", threshold=0.0))
