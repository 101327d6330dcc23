"""The per-scan optimisation loop (§0.5, §0.6, §1.7).

Everything stays on the training device: the batch draw, the dynamic nearest neighbour (chunked
brute force on a GPU), the loss and the optimiser step. The only host reads are the progress
ticks and the loss history, which is kept as device tensors and read once at the end.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import nn

from . import checkpoints
from .checkpoints import Checkpoint
from .config import LossConfig, TrainConfig, check_choices
from .errors import InputError
from .fields.base import normalize
from .fields.mlp import value_and_grad
from .geometry.neighbors import NearestIndex
from .losses import (consistency_chamfer_loss, eikonal_loss, far_field_loss, global_shape_loss,
                     on_surface_loss, pull_loss, tangent_loss, tangent_residual, warm_start_loss)
from .progress import QUIET, Progress


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


@contextmanager
def cpu_threads(n: int):
    """Run the block with ``n`` PyTorch CPU threads (``n ≤ 0``: unchanged), restoring the count after."""
    before = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def make_optimizer(params, device: torch.device, fused: bool) -> torch.optim.Adam:
    """Adam with the reference hyper-parameters (§1.7). ``fused`` uses PyTorch's single-kernel
    implementation where the device has one (CPU and CUDA): the same update, fewer operations."""
    fused = fused and device.type in ("cpu", "cuda")
    return torch.optim.Adam(params, lr=0.0, betas=(0.9, 0.999), eps=1e-8, weight_decay=0.0,
                            **({"fused": True} if fused else {}))


@dataclass
class TrainingData:
    """Unit-space training samples on the training device."""

    surface: torch.Tensor            # (N, 3) surface rows P
    queries: torch.Tensor            # (T, 3)
    anchors: torch.Tensor            # (G, 3)
    anchor_targets: torch.Tensor     # (G,)
    static_targets: torch.Tensor | None = None  # (T, 3) t(q), for the pull and CAP-UDF losses
    static_distance: torch.Tensor | None = None  # (T,) what the warm start and the far term regress u on

    def set_nearest_targets(self) -> None:
        """``static_targets`` = the nearest surface row ``t(q)`` of every query (§1.3 step 5) and
        ``static_distance`` = ``‖q − t(q)‖`` (the ``point`` distance target)."""
        idx = NearestIndex(self.surface).query(self.queries).to(self.surface.device)
        self.static_targets = self.surface[idx]
        self.static_distance = (self.queries - self.static_targets).norm(dim=1)


@dataclass
class TrainResult:
    seconds: float
    iterations: int
    history: dict[str, list[float]] = field(default_factory=dict)


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

    def step(self, i: int, terms: dict[str, torch.Tensor]) -> None:
        """Record after the 0-based step ``i``; stop (:class:`InputError`) when the loss is no longer
        finite (checked at the recorded steps only: one host read every ``log_every`` steps)."""
        if i % self.log_every == 0 or i == self.iters - 1:
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
            line += ("; the robust preset (the default) takes about a minute for 100,000 points on a "
                     "CPU, a GPU runs this preset in minutes")
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


def loss_terms(net: nn.Module, q: torch.Tensor, batch: torch.Tensor, data: TrainingData,
               cfg: LossConfig, nn_index: NearestIndex, anchor_rows: torch.Tensor | None = None,
               explicit: bool = True, warm: bool = False,
               surface_rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """All active loss terms for one batch of queries ``q`` (K, 3) (rows ``batch`` of the store),
    plus ``total``. Pure function of the network's current weights. ``anchor_rows``: the anchors
    that enter ``L_GS`` (all when ``None``); ``surface_rows``: the surface points that enter ``L_OS``
    and ``L_Eik`` (all when ``None``); ``explicit``: the hand-written input gradient
    (:func:`value_and_grad`) instead of autograd's double backward; ``warm``: the warm-start term
    ``mean |u(q) − d(q)|`` (``d``: ``data.static_distance``, ``loss.distance_target``) replaces the
    main loss."""
    if warm:
        terms = {"warm": warm_start_loss(net(q), data.static_distance[batch])}
        return _with_regularisers(net, data, cfg, terms, terms["warm"], None, anchor_rows, explicit,
                                  surface_rows)
    u, g = value_and_grad(net, q, create_graph=True, explicit=explicit)
    g_hat = normalize(g)
    moved = q - u[:, None] * g_hat
    terms: dict[str, torch.Tensor] = {}
    if cfg.kind == "tangent":
        foot = data.surface[nn_index.query(moved).to(data.surface.device)]
        terms["tangent"] = tangent_loss(tangent_residual(q, u, g_hat, foot), cfg.tangent_norm)
        total = cfg.lambda_tangent * terms["tangent"]
        if cfg.lambda_far:
            terms["far"] = far_field_loss(u, data.static_distance[batch], cfg.far_threshold)
            total = total + cfg.lambda_far * terms["far"]
    elif cfg.kind == "pull":
        terms["pull"] = pull_loss(moved, data.static_targets[batch], cfg.pull_norm)
        total = terms["pull"]
    elif cfg.kind == "capudf":
        terms["cd"] = consistency_chamfer_loss(data.static_targets[batch], moved)
        total = terms["cd"]
    else:
        raise ValueError(f"unknown loss kind {cfg.kind!r}")
    return _with_regularisers(net, data, cfg, terms, total, g, anchor_rows, explicit, surface_rows)


def _with_regularisers(net: nn.Module, data: TrainingData, cfg: LossConfig, terms: dict[str, torch.Tensor],
                       total: torch.Tensor, g: torch.Tensor | None, anchor_rows: torch.Tensor | None,
                       explicit: bool, surface_rows: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Add ``L_GS``, ``L_OS`` and ``L_Eik`` (their λ permitting) to ``total``; ``terms`` gets each and
    ``total``. ``g``: the batch's input gradients, which ``L_Eik`` needs; ``surface_rows``: the
    surface points ``L_OS`` and ``L_Eik`` see (all when ``None``)."""
    if cfg.lambda_gs and len(data.anchors):
        if anchor_rows is None:
            terms["gs"] = global_shape_loss(net(data.anchors), data.anchor_targets, cfg.gs_form)
        else:
            terms["gs"] = global_shape_loss(net(data.anchors[anchor_rows]), data.anchor_targets[anchor_rows],
                                            cfg.gs_form)
        total = total + cfg.lambda_gs * terms["gs"]
    if cfg.lambda_os or cfg.lambda_eik:
        need_grad = bool(cfg.lambda_eik)
        surface = data.surface if surface_rows is None else data.surface[surface_rows]
        p = surface.detach().clone().requires_grad_(need_grad)
        if need_grad:
            u_p, g_p = value_and_grad(net, p, create_graph=True, explicit=explicit)
        else:
            u_p = net(p)
        if cfg.lambda_os:
            terms["os"] = on_surface_loss(u_p)
            total = total + cfg.lambda_os * terms["os"]
        if cfg.lambda_eik and g is not None:
            terms["eik"] = eikonal_loss(g_p, g)
            total = total + cfg.lambda_eik * terms["eik"]
    terms["total"] = total
    return terms


def train(net: nn.Module, data: TrainingData, loss_cfg: LossConfig, train_cfg: TrainConfig,
          seed: int, progress: Progress = QUIET, log_every: int = 100,
          expand: Callable[[nn.Module, TrainingData], torch.Tensor] | None = None,
          checkpoint: Checkpoint | None = None) -> TrainResult:
    """Optimise ``net`` in place on ``data`` for ``train_cfg.iters`` iterations (Adam, §1.7).

    ``train_cfg.step``: ``optimised`` (hand-written input gradient, fused Adam) or ``plain``
    (autograd double backward, PyTorch's default Adam); both compute the same losses and updates.
    ``train_cfg.sampler`` picks the batch draw (:data:`SAMPLERS`); ``loss_cfg.gs_anchors > 0``
    evaluates ``L_GS`` on that many anchors drawn at random each step instead of all of them, and
    ``loss_cfg.os_rows > 0`` ``L_OS`` and ``L_Eik`` on that many surface points (drawn after them);
    the first ``loss_cfg.warm_start`` (a fraction) of the steps regress ``u`` on the static distance
    to ``P`` instead of the main loss (needs ``data.static_targets``).

    ``expand`` (CAP-UDF's progressive expansion, §3.4): called once after ``train_cfg.expand_at``
    completed steps with the network and the data; it returns the new static targets (T, 3), and the
    batch becomes ``train_cfg.expand_batch``. The optimiser state and the schedule carry over.

    ``checkpoint``: save the loop's state every ``checkpoint.every`` steps, and with
    ``checkpoint.resume`` start from the saved state (:mod:`~ultraboneudf.checkpoints`): the
    result equals the uninterrupted run's."""
    device = data.queries.device
    generator = torch.Generator(device=device).manual_seed(seed)
    check_choices(train_cfg)
    check_choices(loss_cfg)
    make_sampler = SAMPLERS[train_cfg.sampler]
    sampler = make_sampler(len(data.queries), train_cfg.batch, generator, device)
    nn_index = NearestIndex(data.surface)
    explicit = train_cfg.step == "optimised"
    opt = make_optimizer(net.parameters(), device, fused=explicit)
    n_anchors = len(data.anchors)
    gs_rows = loss_cfg.gs_anchors if 0 < loss_cfg.gs_anchors < n_anchors else 0
    n_surface = len(data.surface)
    os_rows = (loss_cfg.os_rows if (loss_cfg.lambda_os or loss_cfg.lambda_eik)
               and 0 < loss_cfg.os_rows < n_surface else 0)
    iters = train_cfg.iters
    warm_steps = round(loss_cfg.warm_start * iters)
    if (warm_steps > 0 or loss_cfg.lambda_far) and data.static_distance is None:
        raise ValueError("loss.warm_start and loss.lambda_far need the static distances in the "
                         "training data")
    expands = expand is not None and train_cfg.expand_at > 0
    stamp = (checkpoints.fingerprint(data.surface, data.queries, data.anchors, loss_cfg, train_cfg, seed,
                                     sum(p.numel() for p in net.parameters()))
             if checkpoint is not None else "")
    start, resumed = 0, None
    if checkpoint is not None and checkpoint.resume and checkpoint.path.exists():
        resumed = checkpoints.load(checkpoint.path, stamp)
        start = int(resumed["step"])
        net.load_state_dict(resumed["net"])
        opt.load_state_dict(resumed["optimizer"])
        generator.set_state(resumed["generator"])
        if expands and start > train_cfg.expand_at:
            data.static_targets = resumed["static_targets"].to(device)
            sampler = make_sampler(len(data.queries), train_cfg.expand_batch, generator, device)
        sampler.load_state(resumed["sampler"])
        progress.log(f"resumed from {checkpoint.path} at step {start:,} of {iters:,}")
    net.train()
    threads = train_cfg.threads if device.type == "cpu" else 0
    with cpu_threads(threads), progress.stage("training", iters, start=start) as advance:
        # the pace of the last phase: after the warm start, and after CAP-UDF's larger second batch
        steady = max(warm_steps, train_cfg.expand_at if expands else 0, start)
        log = LoopLog(iters, advance, device, log_every, lr=train_cfg.lr, progress=progress,
                      steady_from=steady)
        if resumed is not None:
            log.resume(resumed["history"], float(resumed["seconds"]))
        for i in range(start, iters):
            if expands and i == train_cfg.expand_at:
                net.eval()
                data.static_targets = expand(net, data)
                net.train()
                sampler = make_sampler(len(data.queries), train_cfg.expand_batch, generator, device)
            for group in opt.param_groups:
                group["lr"] = learning_rate(i, train_cfg.lr, train_cfg.warmup, iters)
            batch = sampler()
            opt.zero_grad(set_to_none=True)
            anchor_rows = (torch.randint(0, n_anchors, (gs_rows,), generator=generator, device=device)
                           if gs_rows else None)
            surface_rows = (torch.randint(0, n_surface, (os_rows,), generator=generator, device=device)
                            if os_rows else None)
            terms = loss_terms(net, data.queries[batch], batch, data, loss_cfg, nn_index, anchor_rows,
                               explicit, warm=i < warm_steps, surface_rows=surface_rows)
            terms["total"].backward()
            opt.step()
            log.step(i, terms)
            if checkpoint is not None and checkpoint.every and (i + 1) % checkpoint.every == 0 \
                    and i + 1 < iters:
                checkpoints.save(checkpoint.path, {
                    "fingerprint": stamp, "step": i + 1, "net": net.state_dict(),
                    "optimizer": opt.state_dict(), "generator": generator.get_state(),
                    "sampler": sampler.state(), "history": log.history_so_far(),
                    "seconds": log.elapsed(),
                    **({"static_targets": data.static_targets.cpu()}
                       if expands and i + 1 > train_cfg.expand_at else {})})
    seconds, history = log.finish()
    net.eval()
    return TrainResult(seconds=seconds, iterations=iters, history=history)
