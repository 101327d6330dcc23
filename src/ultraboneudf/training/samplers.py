"""Batch draws and the learning-rate schedule of the training loop (§0.5, §0.6)."""

from __future__ import annotations

import math

import torch


def learning_rate(i: int, lr0: float, warmup: int, total: int) -> float:
    """Warm-up + cosine schedule of §0.6 for the 0-based iteration ``i`` (``lr(0) = 0``)."""
    if i < warmup:
        return lr0 * i / warmup
    return lr0 * 0.5 * (1.0 + math.cos(math.pi * (i - warmup) / max(1, total - warmup)))


class StridedSampler:
    """The reference's batch draw (§0.5): one residue ``r`` mod 10 and ``K`` distinct ``j`` in
    ``[0, R)``, ``R = ⌊(T − 1)/10⌋``; indices ``10·j + r``. Draws on ``device`` from ``generator``."""

    def __init__(self, total: int, batch: int, generator: torch.Generator, device: torch.device) -> None:
        self.rows = (total - 1) // 10
        if self.rows < 1:
            raise ValueError(f"too few stored queries ({total}) for the strided sampler")
        self.batch = min(batch, self.rows)
        self.generator = generator
        self.device = device

    def __call__(self) -> torch.Tensor:
        r = torch.randint(0, 10, (1,), generator=self.generator, device=self.device)
        j = torch.randperm(self.rows, generator=self.generator, device=self.device)[: self.batch]
        return 10 * j + r

    def state(self) -> dict:
        """What a checkpoint keeps of the sampler besides its generator: nothing (each draw is fresh)."""
        return {}

    def load_state(self, state: dict) -> None:
        """Inverse of :meth:`state`."""


class EpochSampler:
    """Consecutive batches of one random permutation of all ``total`` stored queries, redrawn when
    used up: every query is seen once per pass, at the cost of one permutation per pass instead of
    one per step (the ``fast`` preset's draw; the strided draw costs a permutation every step)."""

    def __init__(self, total: int, batch: int, generator: torch.Generator, device: torch.device) -> None:
        if total < 1:
            raise ValueError("no stored queries to sample")
        self.total, self.batch = total, min(batch, total)
        self.generator, self.device = generator, device
        self.order = torch.empty(0, dtype=torch.long, device=device)
        self.pos = 0

    def __call__(self) -> torch.Tensor:
        if self.pos + self.batch > len(self.order):
            self.order = torch.randperm(self.total, generator=self.generator, device=self.device)
            self.pos = 0
        rows = self.order[self.pos:self.pos + self.batch]
        self.pos += self.batch
        return rows

    def state(self) -> dict:
        """The current pass's permutation and position (for a checkpoint)."""
        return {"order": self.order.cpu(), "pos": self.pos}

    def load_state(self, state: dict) -> None:
        """Inverse of :meth:`state`."""
        self.order, self.pos = state["order"].to(self.device), int(state["pos"])


SAMPLERS = {"strided": StridedSampler, "epoch": EpochSampler}
