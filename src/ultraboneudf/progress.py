"""Progress reporting on stderr (rich), silenced by ``quiet``.

Every long stage takes a :class:`Progress` and reports through :meth:`Progress.stage`, which yields an
``advance(n)`` callable. Calling it costs a few microseconds; hot loops should call it every few
iterations rather than every one.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as _RichProgress


class Progress:
    """A progress reporter; ``Progress(quiet=True)`` prints nothing."""

    def __init__(self, quiet: bool = False) -> None:
        self.quiet = quiet
        self._console = Console(file=sys.stderr)

    @contextmanager
    def stage(self, description: str, total: float | None = None) -> Iterator[Callable[[float], None]]:
        """Show one bar for a stage of ``total`` steps (``None``: unknown); yields ``advance(n=1)``."""
        if self.quiet:
            yield lambda n=1: None
            return
        columns = [
            TextColumn("[bold]{task.description:<12}"),
            BarColumn(),
            MofNCompleteColumn() if total is not None else TaskProgressColumn(),
            TextColumn("elapsed"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
        ]
        with _RichProgress(*columns, console=self._console, transient=False) as bar:
            task = bar.add_task(description, total=total)
            yield lambda n=1: bar.advance(task, n)
            if total is not None:
                bar.update(task, completed=total)

    def log(self, message: str) -> None:
        """One line of information on stderr (not shown when quiet)."""
        if not self.quiet:
            self._console.print(message, highlight=False)


QUIET = Progress(quiet=True)
