"""The training loop's bookkeeping: loss history, progress, divergence check, time estimate."""

from __future__ import annotations

import time
from typing import Callable

import torch

from ..errors import InputError
from ..progress import QUIET, Progress


ESTIMATE_AFTER_S = 2.0
"""Seconds of steady training after which :class:`LoopLog` prints its one-line estimate."""

SLOW_RUN_S = 600.0
"""A CPU training estimate above this also names the faster preset."""


class LoopLog:
    """Bookkeeping shared by the training loops: the loss terms every ``log_every`` steps (and the
    last) kept as device tensors and read once at the end, progress ticks, the wall time of the
    loop, synchronised with the device, and one line through ``progress`` after the first seconds
    of steady steps with the time the training will take at that pace. ``steady_from``: the first
    step of the main loss (the warm-start steps before it are cheaper and would flatter the pace)."""

    def __init__(self, iters: int, advance: Callable[[float], None], device: torch.device,
                 log_every: int, lr: float | None = None, progress: Progress = QUIET,
                 steady_from: int = 0) -> None:
        self.iters, self.advance, self.device, self.log_every = iters, advance, device, log_every
        self.lr, self.progress, self.steady_from = lr, progress, steady_from
        self.tick = max(1, min(50, iters // 100))
        self.terms: dict[str, list[torch.Tensor]] = {}
        self.start = time.perf_counter()
        self._steady: float | None = None      # when the first (allocating) steps were over
        self._estimated = progress.quiet

    def records(self, i: int) -> bool:
        """Whether the loss terms of the 0-based step ``i`` go into the history."""
        return i % self.log_every == 0 or i == self.iters - 1

    def step(self, i: int, terms: dict[str, torch.Tensor]) -> None:
        """Record after the 0-based step ``i``; stop (:class:`InputError`) when the loss is no longer
        finite (checked at the recorded steps only: one host read every ``log_every`` steps)."""
        if self.records(i):
            for key, value in terms.items():
                self.terms.setdefault(key, []).append(value.detach())
            if not bool(torch.isfinite(terms["total"]).all()):
                hint = f"; lower train.lr (now {self.lr:g})" if self.lr is not None else ""
                raise InputError(f"training diverged: the loss is not finite at step {i + 1} of "
                                 f"{self.iters}{hint}")
        if (i + 1) % self.tick == 0:
            self.advance(self.tick)
        if not self._estimated:
            self._estimate(i)

    def _estimate(self, i: int) -> None:
        first = min(self.steady_from + 4, self.iters - 1)
        if i < first:
            return
        now = time.perf_counter()
        if i == first:
            self._steady = now
            return
        if now - self._steady < ESTIMATE_AFTER_S:   # a run shorter than that needs no estimate
            return
        if self.device.type == "cuda":  # once: the queued steps are part of the pace
            torch.cuda.synchronize(self.device)
            now = time.perf_counter()
        self._estimated = True
        pace = (now - self._steady) / (i - first)
        left = pace * (self.iters - 1 - i)
        where = "CPU" if self.device.type == "cpu" else "GPU"
        line = (f"estimate: training takes about {_duration(now - self.start + left)} on this {where} "
                f"({self.iters:,} steps at {_duration(pace, fine=True)} each); then the mesh is extracted")
        if self.device.type == "cpu" and left > SLOW_RUN_S:
            line += ("; the robust preset (the default) is made for a CPU's budget, and a GPU runs "
                     "this preset far faster")
        self.progress.log(line)

    def resume(self, history: dict[str, list[float]], seconds: float) -> None:
        """Continue a checkpointed run: its history so far and the seconds it trained."""
        self.terms = {k: [torch.tensor(v, device=self.device) for v in values] for k, values in history.items()}
        self.start = time.perf_counter() - seconds

    def history_so_far(self) -> dict[str, list[float]]:
        """The recorded loss terms as plain lists (one host read; for a checkpoint)."""
        return {k: torch.stack(v).cpu().tolist() for k, v in self.terms.items()}

    def elapsed(self) -> float:
        """Seconds of training so far, this run's and a resumed run's before it."""
        return time.perf_counter() - self.start

    def finish(self) -> tuple[float, dict[str, list[float]]]:
        """Seconds since the start and the history as plain lists (one host read)."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return self.elapsed(), self.history_so_far()


def _duration(seconds: float, fine: bool = False) -> str:
    """``0.8 ms``, ``42 s``, ``3 min``, ``1 h 20 min``: as precise as a person plans with."""
    if fine and seconds < 1.0:
        return f"{seconds * 1e3:.3g} ms"
    if seconds < 90:
        return f"{seconds:.2g} s" if fine and seconds < 10 else f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{int(seconds // 3600)} h {round(seconds % 3600 / 60)} min"
