import io
from types import SimpleNamespace

import pytest

from ultraboneudf.progress import Progress, time_left


def test_time_left_is_the_elapsed_time_scaled_by_the_work_left():
    assert time_left(10.0, 25, 100) == pytest.approx(30.0)
    assert time_left(10.0, 100, 100) == 0.0
    assert time_left(10.0, 0, 100) is None and time_left(10.0, 5, None) is None


def test_without_a_terminal_progress_is_plain_lines_with_the_time_left():
    out = io.StringIO()
    progress = Progress(stream=out, interval=0.0)
    with progress.stage("training", 4) as advance:
        for _ in range(4):
            advance(1)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("training: 1/4 (25%), 0:00:00 elapsed, about 0:00:00 left")
    assert len(lines) == 5 and lines[-1].endswith("(done)") and "4/4 (100%)" in lines[-1]
    assert "\x1b" not in out.getvalue()                    # no terminal escapes in a log file


def test_plain_lines_write_large_counts_in_full_and_no_count_for_a_stage_without_steps():
    out = io.StringIO()
    progress = Progress(stream=out, interval=0.0)
    with progress.stage("distances", 7_011_840) as advance:
        advance(5_704_150)
    with progress.stage("ground truth"):
        pass
    with progress.stage("points") as advance:
        advance(2.5)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("distances: 5,704,150/7,011,840 (81%), ")
    assert lines[1].startswith("distances: 7,011,840/7,011,840 (100%), ") and "e+" not in out.getvalue()
    assert lines[2].startswith("ground truth: 0:00:00 elapsed (done)")
    assert lines[-1].startswith("points: 2.5, ")


def test_lines_come_at_most_once_per_interval_and_quiet_prints_nothing():
    out = io.StringIO()
    with Progress(stream=out, interval=3600.0).stage("extraction", 1000) as advance:
        for _ in range(1000):
            advance(1)
    assert out.getvalue().splitlines() == [out.getvalue().splitlines()[-1]]   # only the final line
    quiet = io.StringIO()
    with Progress(quiet=True, stream=quiet).stage("x", 3) as advance:
        advance(3)
    assert quiet.getvalue() == ""


def _estimates(monkeypatch, iters, step_s, after_s, steps=None, steady_from=0):
    """The lines a training log prints over ``steps`` steps whose ``i``-th takes ``step_s(i)`` seconds
    of a fake clock (``ESTIMATE_AFTER_S`` = ``after_s``)."""
    import torch

    from ultraboneudf.training import log as training

    clock = [0.0]
    monkeypatch.setattr(training, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(training, "ESTIMATE_AFTER_S", after_s)
    out = io.StringIO()
    log = training.LoopLog(iters, lambda n: None, torch.device("cpu"), 100,
                           progress=Progress(stream=out, interval=3600.0), steady_from=steady_from)
    for i in range(iters if steps is None else steps):
        clock[0] += step_s(i)
        log.step(i, {"total": torch.tensor(1.0)})
    return [ln for ln in out.getvalue().splitlines() if ln.startswith("estimate:")]


def test_training_prints_one_estimate_after_its_first_seconds(monkeypatch):
    lines = _estimates(monkeypatch, 400, lambda i: 0.01, 0.05)
    assert len(lines) == 1
    assert "training takes about 4 s on this CPU (400 steps at 10 ms each)" in lines[0]
    assert "robust preset" not in lines[0]         # named only when the run is long


def test_a_long_cpu_run_names_the_faster_preset(monkeypatch):
    lines = _estimates(monkeypatch, 30_000, lambda i: 0.12, 0.5, steps=12)
    assert lines[0].startswith("estimate: training takes about 60 min on this CPU (30,000 steps at 120 ms")
    assert "robust preset (the default)" in lines[0]


def test_the_estimate_waits_for_the_main_loss(monkeypatch):
    """Warm-start steps are cheaper: the pace is measured on the steps after them."""
    lines = _estimates(monkeypatch, 200, lambda i: 0.001 if i < 100 else 0.01, 0.05, steady_from=100)
    assert len(lines) == 1 and "(200 steps at 10 ms each)" in lines[0]


def test_tree_distances_report_their_rows_and_give_the_same_answer():
    import numpy as np
    from scipy.spatial import cKDTree

    from ultraboneudf.geometry.neighbors import tree_distances

    rng = np.random.default_rng(0)
    ref, query = rng.normal(size=(5000, 3)), rng.normal(size=(250_001, 3))
    done = []
    d = tree_distances(cKDTree(ref), query, workers=1, advance=done.append)
    assert sum(done) == len(query) and len(done) >= 2
    assert np.array_equal(d, tree_distances(cKDTree(ref), query, workers=1))


def test_reading_frames_reports_each_frame(tmp_path):
    import numpy as np

    from ultraboneudf.sweep.formats.images import read_stack, write_png

    paths = []
    for k in range(3):
        paths.append(tmp_path / f"f{k}.png")
        write_png(paths[-1], np.full((4, 5), 10 * k, np.uint8))
    out = io.StringIO()
    stack = read_stack(paths, progress=Progress(stream=out, interval=0.0))
    assert stack.shape == (3, 4, 5) and stack[2, 0, 0] == 20
    assert "read frames: 3/3 (100%)" in out.getvalue().splitlines()[-1]


def test_a_resumed_stage_counts_its_pace_from_the_resumed_steps_only():
    assert time_left(10.0, 150, 300, start=100) == pytest.approx(30.0)   # 50 steps in 10 s, 150 left
    assert time_left(10.0, 100, 300, start=100) is None
    out = io.StringIO()
    with Progress(stream=out, interval=0.0).stage("training", 300, start=150) as advance:
        advance(30)
    first = out.getvalue().splitlines()[0]
    assert first.startswith("training: 180/300 (60%)")
