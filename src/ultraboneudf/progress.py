"""Progress reporting on stderr (rich), silenced by ``quiet``.

Every long stage takes a :class:`Progress` and reports through :meth:`Progress.stage`, which yields an
``advance(n)`` callable. Calling it costs a few microseconds; hot loops should call it every few
iterations rather than every one.

On a terminal each stage is a bar whose time left is the elapsed time scaled by the work left, so
it is known from the first update (rich's own estimate waits for a window of updates that a slow
stage takes minutes to fill). When stderr is a file or a pipe a bar would show nothing until the
stage ends, so a plain line is written every ``interval`` seconds instead.
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from datetime import timedelta
from typing import IO, Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    ProgressColumn,
    Task,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.progress import Progress as _RichProgress
from rich.text import Text


def time_left(elapsed: float, done: float, total: float | None, start: float = 0.0) -> float | None:
    """Seconds left at the pace so far (``None`` until there is a pace or without a total);
    ``start``: steps done before ``elapsed`` began (a resumed run), not part of the pace."""
    if total is None or done <= start or elapsed <= 0:
        return None
    return elapsed * max(total - done, 0.0) / (done - start)


def _clock(seconds: float | None) -> str:
    return "-:--:--" if seconds is None else str(timedelta(seconds=round(seconds)))


def _count(n: float) -> str:
    # whole counts in full (a log reads "5,704,150", not "5.70415e+06"); fractional ones short
    return f"{int(n):,}" if float(n).is_integer() else f"{n:.3g}"


class _TimeLeft(ProgressColumn):
    """The stage's time left from its average pace (see the module doc)."""

    def render(self, task: Task) -> Text:
        return Text(_clock(time_left(task.elapsed or 0.0, task.completed, task.total, task.fields.get("before", 0))),
                    style="progress.remaining")


class Progress:
    """A progress reporter; ``Progress(quiet=True)`` prints nothing.

    ``stream``: where to write (default stderr); ``interval``: seconds between the plain lines
    written when ``stream`` is not a terminal (default: the environment's
    ``ULTRABONEUDF_PROGRESS_S``, else 10)."""

    def __init__(self, quiet: bool = False, stream: IO[str] | None = None, interval: float | None = None) -> None:
        if interval is None:
            try:
                interval = float(os.environ.get("ULTRABONEUDF_PROGRESS_S", 10.0))
            except ValueError:
                interval = 10.0
        self.quiet, self.interval = quiet, interval
        self._console = Console(file=stream if stream is not None else sys.stderr)

    @contextmanager
    def stage(self, description: str, total: float | None = None,
              start: float = 0) -> Iterator[Callable[[float], None]]:
        """Show one bar for a stage of ``total`` steps (``None``: unknown) of which ``start`` were done
        before (a resumed run: shown, not counted in the pace); yields ``advance(n=1)``."""
        if self.quiet:
            yield lambda n=1: None
            return
        if not self._console.is_terminal:
            with self._lines(description, total, start) as advance:
                yield advance
            return
        columns = [
            TextColumn("[bold]{task.description:<12}"),
            BarColumn(),
            MofNCompleteColumn() if total is not None else TaskProgressColumn(),
            TextColumn("elapsed"),
            TimeElapsedColumn(),
            TextColumn("left"),
            _TimeLeft(),
        ]
        with _RichProgress(*columns, console=self._console, transient=False) as bar:
            task = bar.add_task(description, total=total, completed=start, before=start)
            yield lambda n=1: bar.advance(task, n)
            if total is not None:
                bar.update(task, completed=total)

    @contextmanager
    def _lines(self, description: str, total: float | None, before: float = 0) -> Iterator[Callable[[float], None]]:
        start = last = time.perf_counter()
        done = float(before)

        def line(now: float, final: bool = False) -> str:
            elapsed = now - start
            if total:
                count = f"{_count(done)}/{_count(total)} ({100 * done / total:.0f}%), "
            else:  # a stage without steps (nothing counted) shows its time alone
                count = f"{_count(done)}, " if done else ""
            left = None if final else time_left(elapsed, done, total, before)
            tail = " (done)" if final else ("" if left is None else f", about {_clock(left)} left")
            return f"{description}: {count}{_clock(elapsed)} elapsed{tail}"

        def advance(n: float = 1) -> None:
            nonlocal done, last
            done += n
            now = time.perf_counter()
            if now - last >= self.interval:
                last = now
                self._console.print(line(now), highlight=False, soft_wrap=True)

        yield advance
        if total is not None:
            done = total
        self._console.print(line(time.perf_counter(), final=True), highlight=False, soft_wrap=True)

    def log(self, message: str) -> None:
        """One line of information on stderr (not shown when quiet)."""
        if not self.quiet:
            self._console.print(message, highlight=False, soft_wrap=True)  # one line in a log file


QUIET = Progress(quiet=True)
