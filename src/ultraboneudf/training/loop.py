"""The optimisation loop (§0.5, §0.6, §1.7): one loop for one scan and for K scans at once.

Every tensor of a step has a leading scan axis: the K fields (:mod:`.scans`), each scan's batch,
nearest-neighbour feet, anchors and loss terms, so the loss is written once for both. Each scan
draws from its own generator, seeded as a run of that scan alone seeds it, in the same order (its
batch, then its ``L_GS`` anchors, then its ``L_OS`` rows), and the total loss is the sum of the
scans' losses: K scans trained together equal the K runs alone, step for step (tested).

Everything stays on the training device: the batch draw, the dynamic nearest neighbour (chunked
brute force on a GPU), the loss and the optimiser step. The only host reads are the progress
ticks and the loss history, which is kept as device tensors and read once at the end.

On a CUDA device the step runs as one static-shape function (:class:`_StaticStep`), captured in a
CUDA graph after a few eager steps and replayed (:mod:`.graph`); the CPU runs the eager loop, which
the static step equals draw for draw and bit for bit (tested).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch
from torch import nn

from .. import checkpoints
from ..checkpoints import Checkpoint
from ..config import LossConfig, TrainConfig, check_choices
from ..fields.base import normalize
from ..fields.mlp import DistanceMLP
from ..geometry.neighbors import NearestIndex
from ..progress import QUIET, Progress
from .log import LoopLog
from .losses import (consistency_chamfer_loss, eikonal_loss, far_field_loss, global_shape_loss,
                     on_surface_loss, pull_loss, tangent_loss, tangent_residual, warm_start_loss)
from .graph import LrSchedule, Replayer, device_draw, graph_capture_blocker
from .samplers import SAMPLERS, learning_rate
from .scans import OneScan, StackedMLP, evaluate_rows


@contextmanager
def cpu_threads(n: int):
    """Run the block with ``n`` PyTorch CPU threads, but never more than PyTorch's own setting (the
    machine's cores, or what ``OMP_NUM_THREADS`` or ``torch.set_num_threads`` chose), restoring the
    count after; ``n ≤ 0``: unchanged. Yields the count the block runs with."""
    before = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(min(n, before))
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before)


@contextmanager
def flush_denormals(device: torch.device):
    """Run the block with subnormal floats flushed to zero on the CPU (``device`` a CUDA device:
    unchanged), then back to PyTorch's default (off; PyTorch offers no way to read the setting).
    Arithmetic on subnormals runs in microcode on x86 CPUs, many times slower: an optimiser whose
    second moments decay into that range (a saturated sigmoid's gradients, squared) spends most of
    each step there."""
    on = device.type == "cpu" and torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if on:
            torch.set_flush_denormal(False)


def make_optimizer(params, device: torch.device, fused: bool,
                   lr: float | torch.Tensor = 0.0) -> torch.optim.Adam:
    """Adam with the reference hyper-parameters (§1.7). ``fused`` uses PyTorch's single-kernel
    implementation where the device has one (CPU and CUDA): the same update, fewer operations.
    ``lr``: the learning rate, a float the loop sets each step, or a tensor on the device that the
    static step updates in place (fused then, and capturable on CUDA: its step count stays on the
    device, so the update can be captured in a CUDA graph)."""
    fused = fused and device.type in ("cpu", "cuda")
    extra = {"fused": True} if fused else {}
    if isinstance(lr, torch.Tensor) and device.type == "cuda":
        extra["capturable"] = True
    return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=0.0, **extra)


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
class Expansion:
    """CAP-UDF's progressive expansion (§3.4) of one scan's training: after ``at`` completed steps
    ``targets(net, data)`` returns the new static targets (T, 3) and the batch becomes ``batch``;
    the optimiser state and the schedule carry over. ``at ≤ 0``: never."""

    at: int
    batch: int
    targets: Callable[[nn.Module, "TrainingData"], torch.Tensor]


@dataclass
class TrainResult:
    seconds: float
    iterations: int
    history: dict[str, list[float]] = field(default_factory=dict)
    step: str = "eager"
    """How the steps ran: ``eager``, ``cuda graph`` (captured after a few eager steps and
    replayed), or ``eager (why no graph)`` on a CUDA device."""
    threads: int = 0
    """The CPU threads the steps ran with (0 on a GPU): float sums, and so the last digits of a
    run, follow it."""


class _Rows:
    """The points of one loss term for each scan with their targets (``L_GS``: the anchors and their
    targets; ``L_OS``: the surface and zeros): all of them every step (padded to a common count,
    with a mask, where the scans' counts differ), or ``per_step`` drawn at random each step."""

    def __init__(self, points: list[torch.Tensor], targets: list[torch.Tensor], per_step: int) -> None:
        self.counts = [len(p) for p in points]
        self.point_list, self.target_list = points, targets
        self.per_step = per_step if 0 < per_step < min(self.counts) else 0
        self.mask = None
        if len(set(self.counts)) == 1:
            self.points, self.targets = torch.stack(points), torch.stack(targets)
        else:
            k, g, dev = len(points), max(self.counts), points[0].device
            self.points = torch.zeros((k, g, 3), device=dev)
            self.targets = torch.zeros((k, g), device=dev)
            self.mask = torch.zeros((k, g), device=dev)
            for i, (p, t) in enumerate(zip(points, targets)):
                self.points[i, :len(p)], self.targets[i, :len(p)], self.mask[i, :len(p)] = p, t, 1.0

    def draw(self, generators: list[torch.Generator]) -> list[torch.Tensor] | None:
        """This step's rows of each scan (``None``: all of them); draws from each scan's generator."""
        if not self.per_step:
            return None
        return [torch.randint(0, c, (self.per_step,), generator=g, device=p.device)
                for c, g, p in zip(self.counts, generators, self.point_list)]

    def take(self, rows: list[torch.Tensor] | None
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Points (K, S, 3), targets (K, S) and mask (K, S) or ``None`` of ``rows``."""
        if rows is None:
            return self.points, self.targets, self.mask
        return (torch.stack([p[r] for p, r in zip(self.point_list, rows)]),
                torch.stack([t[r] for t, r in zip(self.target_list, rows)]), None)


@dataclass
class StepDraw:
    """What one step draws for every scan: batch rows, ``L_GS`` rows and ``L_OS`` rows (``None``:
    all of them)."""

    batch: list[torch.Tensor]
    anchor_rows: list[torch.Tensor] | None = None
    surface_rows: list[torch.Tensor] | None = None


def loss_terms(model: nn.Module, datas: Sequence[TrainingData], step: StepDraw, cfg: LossConfig,
               indices: Sequence[NearestIndex], anchors: _Rows | None, surface: _Rows | None,
               warm: bool = False) -> dict[str, torch.Tensor]:
    """Every active loss term of one step, each (K,), one per scan, plus ``total``; a pure function
    of the fields' current weights. ``model``: the K fields (:mod:`.scans`); ``step``: the rows the
    step drew; ``anchors`` / ``surface``: the points of ``L_GS`` / of ``L_OS`` and ``L_Eik`` (``None``:
    the term is off); ``warm``: the warm-start term ``mean |u(q) − d(q)|`` (``d``:
    ``data.static_distance``, ``loss.distance_target``) replaces the main loss."""
    weights = model.weights()
    q = torch.stack([d.queries[r] for d, r in zip(datas, step.batch)])          # (K, M, 3)
    static = lambda name: torch.stack([getattr(d, name)[r] for d, r in zip(datas, step.batch)])  # noqa: E731
    terms: dict[str, torch.Tensor] = {}
    # the rows that need values only (L_GS's anchors, L_OS's surface points) share the queries'
    # forward sweep: one set of small matrix products a step instead of three
    extra: list[torch.Tensor] = []
    if anchors is not None:
        pts, tgt, mask = anchors.take(step.anchor_rows)
        extra.append(pts)
    if surface is not None:
        p, _, s_mask = surface.take(step.surface_rows)
        if not cfg.lambda_eik:
            extra.append(p)
    u, g, extra_u = evaluate_rows(model, q, extra, weights, grad=not warm)
    if warm:
        terms["warm"] = warm_start_loss(u, static("static_distance"))
        total = terms["warm"]
    else:
        g_hat = normalize(g)
        moved = q - u[..., None] * g_hat
        if cfg.kind == "tangent":
            foot = torch.stack([d.surface[ix.query(m).to(d.surface.device)]
                                for d, ix, m in zip(datas, indices, moved)])
            terms["tangent"] = tangent_loss(tangent_residual(q, u, g_hat, foot), cfg.tangent_norm)
            total = cfg.lambda_tangent * terms["tangent"]
            if cfg.lambda_far:
                terms["far"] = far_field_loss(u, static("static_distance"), cfg.far_threshold)
                total = total + cfg.lambda_far * terms["far"]
        elif cfg.kind == "pull":
            terms["pull"] = pull_loss(moved, static("static_targets"), cfg.pull_norm)
            total = terms["pull"]
        elif cfg.kind == "capudf":
            targets = static("static_targets")
            terms["cd"] = torch.stack([consistency_chamfer_loss(t, m) for t, m in zip(targets, moved)])
            total = terms["cd"]
        else:
            raise ValueError(f"unknown loss kind {cfg.kind!r}")
    if anchors is not None:
        terms["gs"] = global_shape_loss(extra_u.pop(0), tgt, cfg.gs_form, mask)
        total = total + cfg.lambda_gs * terms["gs"]
    if surface is not None:
        if cfg.lambda_eik:
            u_p, g_p = model.value_and_grad(p, weights)
        else:
            u_p = extra_u.pop(0)
        if cfg.lambda_os:
            terms["os"] = on_surface_loss(u_p, s_mask)
            total = total + cfg.lambda_os * terms["os"]
        if cfg.lambda_eik and g is not None:
            terms["eik"] = eikonal_loss(g_p, g, s_mask)
            total = total + cfg.lambda_eik * terms["eik"]
    terms["total"] = total
    return terms


def train(net: nn.Module, data: TrainingData, loss_cfg: LossConfig, train_cfg: TrainConfig,
          seed: int, progress: Progress = QUIET, log_every: int = 100,
          expansion: Expansion | None = None, checkpoint: Checkpoint | None = None,
          static: bool | None = None) -> TrainResult:
    """Optimise ``net`` (any network of (M, 3) → (M,), skip connections included) in place on
    ``data`` for ``train_cfg.iters`` iterations (Adam, §1.7): the loop of :func:`train_many` with
    one scan.

    ``expansion``: CAP-UDF's progressive expansion (:class:`Expansion`).

    ``checkpoint``: save the loop's state every ``checkpoint.every`` steps, and with
    ``checkpoint.resume`` start from the saved state (:mod:`~ultraboneudf.checkpoints`): the
    result equals the uninterrupted run's.

    ``static``: run the static-shape step (:mod:`.graph`; on CUDA captured in a CUDA graph);
    ``None``: on a CUDA device where it can (``train.cuda_graph``, no expansion or checkpoint),
    else the eager loop. On the CPU the static step runs eagerly and equals the eager loop."""
    model = OneScan(net, explicit=train_cfg.step == "optimised")
    return _loop(model, [data], loss_cfg, train_cfg, [seed], progress, log_every, expansion, checkpoint,
                 static)[0]


def train_many(nets: list[DistanceMLP], datas: list[TrainingData], loss_cfg: LossConfig,
               train_cfg: TrainConfig, seeds: list[int], progress: Progress = QUIET,
               log_every: int = 100, static: bool | None = None
               ) -> tuple[list[DistanceMLP], list[TrainResult]]:
    """Train ``nets[k]`` on ``datas[k]`` with seed ``seeds[k]``, all K at once, their weights stacked
    (:class:`~.scans.StackedMLP`: the same widths, no skip connections). Step for step the result
    equals K runs of :func:`train` (see the module docstring); on CUDA the K scans' step is one
    CUDA graph (``static`` as in :func:`train`).

    ``train_cfg.step``: ``optimised`` (hand-written input gradient, fused Adam) or ``plain``
    (autograd double backward, PyTorch's default Adam); both compute the same losses and updates.
    ``train_cfg.sampler`` picks the batch draw (:data:`~.samplers.SAMPLERS`); ``loss_cfg.gs_anchors
    > 0`` evaluates ``L_GS`` on that many anchors drawn at random each step instead of all of them,
    and ``loss_cfg.os_rows > 0`` ``L_OS`` and ``L_Eik`` on that many surface points (drawn after
    them); the first ``loss_cfg.warm_start`` (a fraction) of the steps regress ``u`` on the static
    distance instead of the main loss (needs ``data.static_distance``).

    Returns the trained networks (new modules) and one :class:`TrainResult` per scan (the shared
    wall time; each scan's own loss history)."""
    if not (len(nets) == len(datas) == len(seeds) >= 1):
        raise ValueError("need one network, one data set and one seed per scan")
    model = StackedMLP(nets, explicit=train_cfg.step == "optimised").to(datas[0].queries.device)
    results = _loop(model, datas, loss_cfg, train_cfg, seeds, progress, log_every, static=static)
    return model.networks(), results


def _eager_reason(device: torch.device, train_cfg: TrainConfig, expansion: Expansion | None,
                  checkpoint: Checkpoint | None) -> str | None:
    """Why the steps of this run cannot be captured in a CUDA graph, or ``None`` when they can."""
    if not train_cfg.cuda_graph:
        return "train.cuda_graph is off"
    if train_cfg.step != "optimised":
        return "train.step=plain steps eagerly"
    if expansion is not None and expansion.at > 0:
        return "CAP-UDF's expansion changes the batch during the run"
    if checkpoint is not None:
        return "checkpoints are saved between eager steps"
    return graph_capture_blocker(device)


def _loop(model: nn.Module, datas: list[TrainingData], loss_cfg: LossConfig, train_cfg: TrainConfig,
          seeds: list[int], progress: Progress, log_every: int,
          expansion: Expansion | None = None, checkpoint: Checkpoint | None = None,
          static: bool | None = None) -> list[TrainResult]:
    """The loop itself, for the K fields of ``model`` (:mod:`.scans`); ``expansion`` and
    ``checkpoint`` with one scan only (:func:`train`); ``static`` as in :func:`train`."""
    check_choices(train_cfg)
    check_choices(loss_cfg)
    if (expansion is not None or checkpoint is not None) and not isinstance(model, OneScan):
        raise ValueError("CAP-UDF's expansion and checkpoints train one scan at a time")
    device = datas[0].queries.device
    reason = _eager_reason(device, train_cfg, expansion, checkpoint)
    if static is None:
        static = reason is None
    elif static and (expansion is not None and expansion.at > 0 or checkpoint is not None):
        raise ValueError("the static step runs without CAP-UDF's expansion and checkpoints")
    generators = [torch.Generator(device=device).manual_seed(s) for s in seeds]
    make_sampler = SAMPLERS[train_cfg.sampler]
    samplers = [make_sampler(len(d.queries), train_cfg.batch, gen, device) for d, gen in zip(datas, generators)]
    indices = [NearestIndex(d.surface) for d in datas]
    iters = train_cfg.iters
    schedule = LrSchedule(train_cfg.lr, train_cfg.warmup, iters, device) if static else None
    opt = make_optimizer(model.parameters(), device, fused=train_cfg.step == "optimised",
                         lr=schedule.lr if static else 0.0)
    warm_steps = round(loss_cfg.warm_start * iters)
    if (warm_steps > 0 or loss_cfg.lambda_far) and any(d.static_distance is None for d in datas):
        raise ValueError("loss.warm_start and loss.lambda_far need the static distances in the "
                         "training data")
    anchors = (_Rows([d.anchors for d in datas], [d.anchor_targets for d in datas], loss_cfg.gs_anchors)
               if all(len(d.anchors) for d in datas) else None)
    surface = (_Rows([d.surface for d in datas], [torch.zeros(len(d.surface), device=device) for d in datas],
                     loss_cfg.os_rows) if loss_cfg.lambda_os or loss_cfg.lambda_eik else None)
    expands = expansion is not None and expansion.at > 0
    net = model.net if isinstance(model, OneScan) else None
    data = datas[0]
    stamp = (checkpoints.fingerprint(data.surface, data.queries, data.anchors, loss_cfg, train_cfg, seeds[0],
                                     sum(p.numel() for p in net.parameters()),
                                     [expansion.at, expansion.batch] if expands else None)
             if checkpoint is not None else "")
    start, resumed = 0, None
    if checkpoint is not None and checkpoint.resume and checkpoint.path.exists():
        resumed = checkpoints.load(checkpoint.path, stamp)
        start = int(resumed["step"])
        net.load_state_dict(resumed["net"])
        opt.load_state_dict(resumed["optimizer"])
        generators[0].set_state(resumed["generator"])
        if expands and start > expansion.at:
            data.static_targets = resumed["static_targets"].to(device)
            samplers[0] = make_sampler(len(data.queries), expansion.batch, generators[0], device)
        samplers[0].load_state(resumed["sampler"])
        progress.log(f"resumed from {checkpoint.path} at step {start:,} of {iters:,}")
    model.train()
    threads = train_cfg.threads if device.type == "cpu" else 0
    mode = "eager"
    if not static and reason is not None and device.type == "cuda":  # the CPU always steps eagerly
        progress.log(f"training: eager steps ({reason})")
        mode = f"eager ({reason})"
    with cpu_threads(threads) as used, progress.stage("training", iters, start=start) as advance:
        # the pace of the last phase: after the warm start, and after CAP-UDF's larger second batch
        steady = max(warm_steps, expansion.at if expands else 0, start)
        log = LoopLog(iters, advance, device, log_every, lr=train_cfg.lr, progress=progress,
                      steady_from=steady)
        if resumed is not None:
            log.resume(resumed["history"], float(resumed["seconds"]))
        if static:
            step = _StaticStep(model, datas, loss_cfg, indices, anchors, surface, samplers, generators, opt,
                               schedule)
            mode = _static_loop(step, iters, warm_steps, device, log, generators, progress,
                                capture=reason is None)
        else:
            for i in range(start, iters):
                if expands and i == expansion.at:
                    net.eval()
                    data.static_targets = expansion.targets(net, data)
                    net.train()
                    samplers[0] = make_sampler(len(data.queries), expansion.batch, generators[0], device)
                for group in opt.param_groups:
                    group["lr"] = learning_rate(i, train_cfg.lr, train_cfg.warmup, iters)
                # each scan's draws in the order of a run of it alone: batch, anchors, surface rows
                step = StepDraw([s() for s in samplers])
                if anchors is not None:
                    step.anchor_rows = anchors.draw(generators)
                if surface is not None:
                    step.surface_rows = surface.draw(generators)
                opt.zero_grad(set_to_none=True)
                terms = loss_terms(model, datas, step, loss_cfg, indices,
                                   anchors if loss_cfg.lambda_gs else None, surface, warm=i < warm_steps)
                terms["total"].sum().backward()
                opt.step()
                log.step(i, terms)
                if checkpoint is not None and checkpoint.every and (i + 1) % checkpoint.every == 0 \
                        and i + 1 < iters:
                    checkpoints.save(checkpoint.path, {
                        "fingerprint": stamp, "step": i + 1, "net": net.state_dict(),
                        "optimizer": opt.state_dict(), "generator": generators[0].get_state(),
                        "sampler": samplers[0].state(), "history": log.history_so_far(),
                        "seconds": log.elapsed(),
                        **({"static_targets": data.static_targets.cpu()}
                           if expands and i + 1 > expansion.at else {})})
    seconds, history = log.finish()
    model.eval()
    return [TrainResult(seconds=seconds, iterations=iters,
                        history={key: [row[k] for row in values] for key, values in history.items()}, step=mode,
                        threads=used if device.type == "cpu" else 0)
            for k in range(len(datas))]


class _StaticStep:
    """One training step of fixed shapes with all its state on the device (:mod:`.graph`): the
    eager loop's step, draw for draw and operation for operation, with the learning rate from
    ``schedule`` and the epoch sampler's permutation drawn between steps (:meth:`before`)."""

    def __init__(self, model: nn.Module, datas: list[TrainingData], loss_cfg: LossConfig,
                 indices: list[NearestIndex], anchors: _Rows | None, surface: _Rows | None,
                 samplers: list, generators: list[torch.Generator], opt: torch.optim.Optimizer,
                 schedule: LrSchedule) -> None:
        self.model, self.datas, self.loss_cfg, self.indices = model, datas, loss_cfg, indices
        self.anchors, self.surface, self.generators = anchors, surface, generators
        self.opt, self.schedule = opt, schedule
        self.draws = [device_draw(s) for s in samplers]

    def before(self) -> None:
        """The host's part of the next step, outside any graph."""
        for draw in self.draws:
            draw.before()

    def __call__(self, warm: bool) -> dict[str, torch.Tensor]:
        self.schedule.advance()
        step = StepDraw([draw() for draw in self.draws])
        if self.anchors is not None:
            step.anchor_rows = self.anchors.draw(self.generators)
        if self.surface is not None:
            step.surface_rows = self.surface.draw(self.generators)
        self.opt.zero_grad(set_to_none=True)
        terms = loss_terms(self.model, self.datas, step, self.loss_cfg, self.indices,
                           self.anchors if self.loss_cfg.lambda_gs else None, self.surface, warm=warm)
        terms["total"].sum().backward()
        self.opt.step()
        return terms


def _static_loop(step: _StaticStep, iters: int, warm_steps: int, device: torch.device, log: LoopLog,
                 generators: list[torch.Generator], progress: Progress, capture: bool) -> str:
    """Run ``step`` for every step: one :class:`~.graph.Replayer` (one CUDA graph with ``capture``)
    for the warm-start steps and one for the main loss. Returns how the steps ran (see
    :class:`TrainResult`)."""
    runners: dict[bool, Replayer] = {}
    failed = None
    for i in range(iters):
        step.before()
        warm = i < warm_steps
        runner = runners.get(warm)
        if runner is None:
            runners.clear()   # the warm start is over: its graph's memory goes back
            runner = runners[warm] = Replayer(lambda w=warm: step(w), device, generators,
                                              capture=capture and failed is None)
        terms = runner()
        if runner.failed and failed is None:
            failed = runner.failed
            progress.log(f"training: eager steps from step {i + 1:,} on (the CUDA graph capture failed: {failed})")
        # a replay's results are overwritten by the next replay: the history keeps copies
        log.step(i, {k: v.clone() for k, v in terms.items()} if log.records(i) else terms)
    if failed is not None:
        return f"eager (the CUDA graph capture failed: {failed})"
    return "cuda graph" if capture else "eager"
