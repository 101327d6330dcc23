import io

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
