"""The training step as one static-shape function, captured once in a CUDA graph and replayed.

An eager step launches a few hundred small kernels, and on a GPU each waits for Python to launch
it. The static step (built in :mod:`.loop`) is the same step with every shape fixed and all its
state on the device: the draws from each scan's own generator, the learning rate read from the
schedule's table by a step counter on the device (:class:`LrSchedule`), the dynamic nearest
neighbour, the losses, and a fused, capturable Adam. Nothing in it reads back to the host, so
:class:`Replayer` runs it eagerly a few times (on a side stream, as CUDA graphs need) and then
captures it in a CUDA graph whose replay is the whole step in one launch.

What must happen between steps is done on the host between replays, at steps known in advance:
the epoch sampler's permutation for a new pass (:class:`EpochDraw`), the switch from the warm
start to the main loss (one graph each), and copying the loss terms of the recorded steps.
"""

from __future__ import annotations

import warnings
from typing import Callable

import torch

from .samplers import EpochSampler, StridedSampler, learning_rate

WARMUP_CALLS = 3
"""Eager calls of a step function before it is captured (lazy initialisations, Adam's state)."""


def graph_capture_blocker(device: torch.device) -> str | None:
    """Why a step with seeded generators cannot be captured in a CUDA graph on ``device``, or
    ``None`` when it can."""
    if device.type != "cuda":
        return "CUDA graphs need a CUDA device"
    if not hasattr(torch.cuda.CUDAGraph, "register_generator_state"):
        return f"PyTorch {torch.__version__} cannot capture draws from a seeded generator in a CUDA graph"
    return None


class LrSchedule:
    """The learning rate of each of ``total`` steps (:func:`~.samplers.learning_rate`) in a table on
    the device, and a step counter on the device that reads it: :meth:`advance` sets :attr:`lr`,
    the tensor the optimiser reads, to the current step's rate and counts the step. The table is
    float64 on the CPU (the same rates as the eager loop's floats, to the bit) and float32 on CUDA
    (what the fused Adam kernel reads)."""

    def __init__(self, lr0: float, warmup: int, total: int, device: torch.device) -> None:
        dtype = torch.float64 if device.type == "cpu" else torch.float32
        rates = [learning_rate(i, lr0, warmup, total) for i in range(total)]
        self.table = torch.tensor(rates, dtype=dtype).to(device)
        self.step = torch.zeros(1, dtype=torch.int64, device=device)
        self.lr = torch.zeros(1, dtype=dtype, device=device)

    def advance(self) -> None:
        self.lr.copy_(self.table.index_select(0, self.step))
        self.step.add_(1)


class StridedDraw:
    """:class:`~.samplers.StridedSampler`'s draw, already of fixed shape and on the device."""

    def __init__(self, sampler: StridedSampler) -> None:
        self.sampler = sampler

    def before(self) -> None:
        """Nothing to do between steps."""

    def __call__(self) -> torch.Tensor:
        return self.sampler()


class EpochDraw:
    """:class:`~.samplers.EpochSampler`'s draw split in two: :meth:`before`, on the host between
    steps, draws the permutation of a new pass into a fixed buffer when the pass is used up (the
    host counts the position, as the sampler does); the call, inside the step, reads the batch at
    a position held on the device. The same rows from the same draws as the sampler."""

    def __init__(self, sampler: EpochSampler) -> None:
        self.sampler = sampler
        dev = sampler.device
        self.order = torch.empty(sampler.total, dtype=torch.int64, device=dev)
        self.offsets = torch.arange(sampler.batch, device=dev)
        self.pos = torch.zeros(1, dtype=torch.int64, device=dev)
        self.host_pos, self.filled = 0, False

    def before(self) -> None:
        s = self.sampler
        if not self.filled or self.host_pos + s.batch > s.total:
            self.order.copy_(torch.randperm(s.total, generator=s.generator, device=s.device))
            self.pos.zero_()
            self.host_pos, self.filled = 0, True
        self.host_pos += s.batch

    def __call__(self) -> torch.Tensor:
        rows = self.order.index_select(0, self.pos + self.offsets)
        self.pos.add_(self.sampler.batch)
        return rows


def device_draw(sampler: StridedSampler | EpochSampler) -> StridedDraw | EpochDraw:
    """The static-step form of a batch sampler."""
    return EpochDraw(sampler) if isinstance(sampler, EpochSampler) else StridedDraw(sampler)


class Replayer:
    """Calls ``fn`` (a step: no host reads, fixed shapes, state in tensors it updates in place):
    eagerly for the first :data:`WARMUP_CALLS` calls, then captured in a CUDA graph, and from then on
    each call is one replay of the graph, whose results are the same tensors each time (copy what
    must outlive the next call). ``capture`` false, or ``device`` not CUDA: every call is eager.
    ``generators``: the CUDA generators ``fn`` draws from, registered with the graph so each replay
    draws on from where the generator stands. A capture that fails leaves the run eager from that
    call on, with the reason in :attr:`failed`."""

    def __init__(self, fn: Callable[[], dict[str, torch.Tensor]], device: torch.device,
                 generators: list[torch.Generator], capture: bool = True) -> None:
        self.fn, self.device, self.generators = fn, device, generators
        self.capture = capture and device.type == "cuda"
        self.calls = 0
        self.graph = None
        self.out: dict[str, torch.Tensor] = {}
        self.failed: str | None = None
        self._states: list[torch.Tensor] = []
        self.stream = torch.cuda.Stream(device) if self.capture else None

    def __call__(self) -> dict[str, torch.Tensor]:
        if self.graph is not None:
            self.graph.replay()
            return self.out
        if not self.capture or self.calls < WARMUP_CALLS:
            self.calls += 1
            return self._eager()
        try:
            self._capture()
        except Exception as error:  # any op that cannot be captured: eager from here on
            self._recover(error)
            return self._eager()
        self.graph.replay()
        return self.out

    def _eager(self) -> dict[str, torch.Tensor]:
        with warnings.catch_warnings():
            # Adam built capturable warns when it steps outside a capture; these steps are meant to
            warnings.filterwarnings("ignore", message=".*capturable.*")
            if self.stream is None:
                return self.fn()
            main = torch.cuda.current_stream(self.device)
            self.stream.wait_stream(main)
            with torch.cuda.stream(self.stream):
                out = self.fn()
            main.wait_stream(self.stream)
            return out

    def _capture(self) -> None:
        self._states = [g.get_state() for g in self.generators]
        graph = torch.cuda.CUDAGraph()
        for g in self.generators:
            graph.register_generator_state(g)
        with torch.cuda.graph(graph):
            out = self.fn()
        self.graph, self.out = graph, out

    def _recover(self, error: Exception) -> None:
        torch.cuda.synchronize(self.device)
        # nothing captured ran; the generators go back to where they stood before the capture
        for g, state in zip(self.generators, self._states):
            g.set_state(state)
        self.capture, self.graph, self.stream = False, None, None
        self.failed = (str(error).strip().splitlines() or [type(error).__name__])[0]
