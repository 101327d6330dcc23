"""Several scans trained at once: K independent UltraBoneUDF fields in one process.

At the ``fast`` preset's batch of 250 queries a training step is mostly fixed overhead (operator
dispatch, the optimiser, the nearest-neighbour call), not arithmetic. Stacking the K networks'
weights into ``(K, out, in)`` tensors runs one batched matrix product per layer for all scans, so
the overhead is paid once per step instead of K times. The scans stay independent: each has its
own data, nearest-neighbour index, batch draw (from its own generator, seeded as :func:`train`
seeds it) and loss; the total loss is their sum, so each network's gradient is its own loss's, and
Adam is element-wise, so one optimiser over the stacked weights is K independent optimisers. Step
for step the result equals K separate :func:`~ultraboneudf.training.train` runs (tested).

Supported: the tangent loss with ``L_GS``, ``L_OS``, the warm start and the far-field term (the
``official``, ``paper``, ``fast`` and ``robust`` presets); networks without skip connections.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from .config import GS_FORMS, LossConfig, TrainConfig, check_choices
from .errors import InputError
from .fields.base import normalize
from .fields.mlp import DistanceMLP
from .geometry.neighbors import NearestIndex
from .losses import far_field_loss, global_shape_loss, tangent_loss, tangent_residual, warm_start_loss
from .progress import QUIET, Progress
from .training import SAMPLERS, LoopLog, TrainingData, TrainResult, cpu_threads, learning_rate, make_optimizer


class StackedMLP(nn.Module):
    """K :class:`DistanceMLP` of the same widths (no skip) as stacked parameters ``v (K, out, in)``,
    ``g (K, out, 1)``, ``bias (K, out)``. Inputs ``(K, M, 3)``, outputs ``(K, M)``."""

    def __init__(self, nets: list[DistanceMLP]) -> None:
        super().__init__()
        first = nets[0]
        if any(n.skip for n in nets):
            raise ValueError("stacked training supports networks without skip connections")
        shapes = [[tuple(p.shape) for p in n.parameters()] for n in nets]
        if any(s != shapes[0] for s in shapes) or any(n.abs_output != first.abs_output for n in nets):
            raise ValueError("stacked networks must have the same widths and output")
        self.abs_output = first.abs_output
        self.weight_norm = [layer.weight_norm for layer in first.layers]
        stack = lambda name, i: nn.Parameter(torch.stack([getattr(n.layers[i], name).detach()  # noqa: E731
                                                          for n in nets]).clone())
        self.v = nn.ParameterList([stack("v", i) for i in range(len(first.layers))])
        self.bias = nn.ParameterList([stack("bias", i) for i in range(len(first.layers))])
        self.g = nn.ParameterList([stack("g", i) if wn else nn.Parameter(torch.zeros(0), requires_grad=False)
                                   for i, wn in enumerate(self.weight_norm)])

    def weights(self) -> list[torch.Tensor]:
        """The effective weights ``(K, out, in)`` of every layer."""
        return [v * (g / v.norm(dim=2, keepdim=True)) if wn else v
                for v, g, wn in zip(self.v, self.g, self.weight_norm)]

    def forward(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None) -> torch.Tensor:
        weights = weights or self.weights()
        h = x
        last = len(weights) - 1
        for i, (w, b) in enumerate(zip(weights, self.bias)):
            h = torch.baddbmm(b[:, None, :], h, w.transpose(1, 2))
            if i < last:
                h = torch.relu(h)
        out = h.squeeze(-1)
        return out.abs() if self.abs_output else out

    def value_and_grad(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """``u`` (K, M) and ``∇u`` (K, M, 3): the hand-written backward sweep of
        :meth:`DistanceMLP.value_and_grad`, batched over the K networks."""
        weights = weights or self.weights()
        h, acts = x, []
        last = len(weights) - 1
        for i, (w, b) in enumerate(zip(weights, self.bias)):
            z = torch.baddbmm(b[:, None, :], h, w.transpose(1, 2))
            if i < last:
                h = torch.relu(z)
                acts.append(h)
        z = z.squeeze(-1)
        u = z.abs() if self.abs_output else z
        d = z.sign()[..., None] if self.abs_output else torch.ones_like(z)[..., None]
        for i in range(last, -1, -1):
            if i < last:
                d = torch.ops.aten.threshold_backward(d, acts[i], 0.0)
            d = torch.bmm(d, weights[i])
        return u, d

    def unstack(self, template: DistanceMLP) -> list[DistanceMLP]:
        """K separate networks (copies of ``template``) holding the trained weights."""
        nets = []
        for k in range(self.v[0].shape[0]):
            net = copy.deepcopy(template)
            with torch.no_grad():
                for layer, v, g, b in zip(net.layers, self.v, self.g, self.bias):
                    layer.v.copy_(v[k])
                    layer.bias.copy_(b[k])
                    if layer.weight_norm:
                        layer.g.copy_(g[k])
            nets.append(net.to(self.v[0].device).eval())
        return nets


def _check(loss_cfg: LossConfig) -> None:
    if loss_cfg.kind != "tangent" or loss_cfg.lambda_eik:
        raise InputError("training several scans at once supports the tangent loss with L_GS, L_OS, "
                         "the warm start and the far-field term (no L_Eik or other loss kinds)")


def train_many(nets: list[DistanceMLP], datas: list[TrainingData], loss_cfg: LossConfig,
               train_cfg: TrainConfig, seeds: list[int], progress: Progress = QUIET,
               log_every: int = 100) -> tuple[list[DistanceMLP], list[TrainResult]]:
    """Train ``nets[k]`` on ``datas[k]`` with seed ``seeds[k]``, all K at once (see the module doc).

    Returns the trained networks (new modules) and one :class:`TrainResult` per scan (the shared
    wall time; each scan's own loss history)."""
    _check(loss_cfg)
    if not (len(nets) == len(datas) == len(seeds) >= 1):
        raise ValueError("need one network, one data set and one seed per scan")
    check_choices(train_cfg)
    check_choices(loss_cfg)
    device = datas[0].queries.device
    k_scans, iters = len(nets), train_cfg.iters
    stacked = StackedMLP(nets).to(device)
    generators = [torch.Generator(device=device).manual_seed(s) for s in seeds]
    samplers = [SAMPLERS[train_cfg.sampler](len(d.queries), train_cfg.batch, gen, device)
                for d, gen in zip(datas, generators)]
    indices = [NearestIndex(d.surface) for d in datas]
    opt = make_optimizer(stacked.parameters(), device, fused=True)
    warm_steps = round(loss_cfg.warm_start * iters)
    if (warm_steps > 0 or loss_cfg.lambda_far) and any(d.static_distance is None for d in datas):
        raise ValueError("loss.warm_start and loss.lambda_far need the static distances")
    anchors = (_Targets([d.anchors for d in datas], [d.anchor_targets for d in datas], loss_cfg.gs_anchors,
                        loss_cfg.gs_form) if loss_cfg.lambda_gs else None)
    on_surface = (_Targets([d.surface for d in datas], [torch.zeros(len(d.surface), device=device) for d in datas],
                           loss_cfg.os_rows) if loss_cfg.lambda_os else None)
    stacked.train()
    threads = train_cfg.threads if device.type == "cpu" else 0
    with cpu_threads(threads), progress.stage("training", iters) as advance:
        log = LoopLog(iters, advance, device, log_every, lr=train_cfg.lr, progress=progress,
                      steady_from=warm_steps)
        for i in range(iters):
            for group in opt.param_groups:
                group["lr"] = learning_rate(i, train_cfg.lr, train_cfg.warmup, iters)
            rows = [s() for s in samplers]
            opt.zero_grad(set_to_none=True)
            terms = _loss_terms(stacked, datas, rows, indices, anchors, on_surface, generators, loss_cfg,
                                i < warm_steps)
            terms["total"].sum().backward()
            opt.step()
            log.step(i, terms)
    seconds, history = log.finish()
    results = [TrainResult(seconds=seconds, iterations=iters,
                           history={key: [row[k] for row in values] for key, values in history.items()})
               for k in range(k_scans)]
    return stacked.unstack(nets[0]), results


class _Targets:
    """Each scan's points with their target values (``L_GS``: anchors and targets; ``L_OS``: the
    surface and zeros), padded to a common count (with a mask), or drawn ``per_step`` at a time.
    ``form``: as :func:`~ultraboneudf.losses.global_shape_loss` pairs outputs and targets."""

    def __init__(self, points: list[torch.Tensor], targets: list[torch.Tensor], per_step: int,
                 form: str = "per_anchor") -> None:
        if form not in GS_FORMS:
            raise ValueError(f"unknown L_GS form {form!r}")
        counts = [len(p) for p in points]
        self.counts, self.point_list, self.target_list, self.form = counts, points, targets, form
        self.per_step = per_step if 0 < per_step < min(counts) else 0
        if not self.per_step:
            g = max(counts)
            dev = points[0].device
            self.points = torch.zeros((len(points), g, 3), device=dev)
            self.targets = torch.zeros((len(points), g), device=dev)
            self.mask = torch.zeros((len(points), g), device=dev)
            for k, (p, t) in enumerate(zip(points, targets)):
                self.points[k, :counts[k]] = p
                self.targets[k, :counts[k]] = t
                self.mask[k, :counts[k]] = 1.0

    def loss(self, net: StackedMLP, weights: list[torch.Tensor],
             generators: list[torch.Generator]) -> torch.Tensor:
        """Per scan (K,): the mean squared error of ``u`` against the targets (§1.6 Eq. 7, Eq. 9)."""
        if self.per_step:
            # the same draw, from the same generator, as train() makes after its batch draw
            rows = [torch.randint(0, c, (self.per_step,), generator=g, device=p.device)
                    for c, g, p in zip(self.counts, generators, self.point_list)]
            pts = torch.stack([p[r] for p, r in zip(self.point_list, rows)])
            tgt = torch.stack([t[r] for t, r in zip(self.target_list, rows)])
            mask = None
        else:
            pts, tgt, mask = self.points, self.targets, self.mask
        return global_shape_loss(net(pts, weights), tgt, self.form, mask)


def _loss_terms(net: StackedMLP, datas: list[TrainingData], rows: list[torch.Tensor],
                indices: list[NearestIndex], anchors: _Targets | None, on_surface: _Targets | None,
                generators: list[torch.Generator], cfg: LossConfig, warm: bool) -> dict[str, torch.Tensor]:
    """Per-scan loss terms, each (K,), as :func:`~ultraboneudf.training.loss_terms` computes them."""
    weights = net.weights()
    q = torch.stack([d.queries[r] for d, r in zip(datas, rows)])
    terms: dict[str, torch.Tensor] = {}
    if warm:
        dist = torch.stack([d.static_distance[r] for d, r in zip(datas, rows)])
        terms["warm"] = warm_start_loss(net(q, weights), dist)
        total = terms["warm"]
    else:
        u, g = net.value_and_grad(q, weights)
        g_hat = normalize(g)
        moved = q - u[..., None] * g_hat
        foot = torch.stack([d.surface[ix.query(m).to(d.surface.device)]
                            for d, ix, m in zip(datas, indices, moved)])
        terms["tangent"] = tangent_loss(tangent_residual(q, u, g_hat, foot), cfg.tangent_norm)
        total = cfg.lambda_tangent * terms["tangent"]
        if cfg.lambda_far:
            dist = torch.stack([d.static_distance[r] for d, r in zip(datas, rows)])
            terms["far"] = far_field_loss(u, dist, cfg.far_threshold)
            total = total + cfg.lambda_far * terms["far"]
    if anchors is not None:
        terms["gs"] = anchors.loss(net, weights, generators)
        total = total + cfg.lambda_gs * terms["gs"]
    if on_surface is not None:
        terms["os"] = on_surface.loss(net, weights, generators)  # zero targets: mean u², Eq. 9
        total = total + cfg.lambda_os * terms["os"]
    terms["total"] = total
    return terms


__all__ = ["StackedMLP", "train_many"]
