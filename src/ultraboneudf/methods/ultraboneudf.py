"""UltraBoneUDF (§1): an MLP unsigned distance field trained with the tangent-plane loss and the
global-shape regulariser; also its ablation variants through ``config.loss`` (kind ``pull``,
λ_OS, λ_Eik, λ_GS) and ``config.model.hidden``."""

from __future__ import annotations

import time

import numpy as np
import torch

from ..config import Config, LossConfig, TrainConfig, check_choices, model_widths, training_schedule
from ..errors import InputError
from ..fields.mlp import DistanceMLP, MLPField, count_parameters
from ..geometry.data_surface import DataSurface
from ..geometry.surface_fit import LocalPlanes
from ..geometry.queries import anchors, gaussian_queries, grid_queries, query_spread, surface_subset_index
from ..checkpoints import Checkpoint
from ..progress import QUIET, Progress
from ..training import TrainingData, TrainResult, train
from .base import Fitted


def prepare(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
            progress: Progress = QUIET, static_targets: bool | None = None,
            timings: dict[str, float] | None = None, planes: LocalPlanes | None = None) -> TrainingData:
    """Surface rows, queries (+ static targets for the pull loss) and anchors, on ``device`` (§1.2–1.4).

    ``points`` is the voxelised, normalised cloud (unit space). Random draws use a NumPy generator
    seeded with ``seed`` so that the samples are identical on every device. ``static_targets``:
    compute ``t(q)`` and the distance target of ``loss.distance_target`` (default: when the loss
    needs them: kinds ``pull`` and ``capudf``, warm start, far-field term). ``planes``: the
    pipeline's local planes of ``points`` (unit space), which the ``surface`` target needs.
    ``timings``: if given, receives the seconds of each step (``subset_s``, ``sigma_s``,
    ``queries_s``, ``anchors_s``, ``static_nn_s``).
    """
    clock = _StageClock(timings, device)
    if static_targets is None:
        static_targets = (cfg.loss.kind in ("pull", "capudf") or cfg.loss.warm_start > 0
                          or cfg.loss.lambda_far > 0)
    check_choices(cfg.loss)
    if static_targets and cfg.loss.distance_target == "surface" and planes is None:
        raise InputError("loss.distance_target=surface needs the local planes: set data.surface_fit_mm > 0")
    d = cfg.data
    rng = np.random.default_rng(seed)
    with progress.stage("sampling", 4) as advance:
        rows = surface_subset_index(points, d.subset, d.subset_threshold, d.fps_sizes, d.max_points,
                                    device=str(device))
        surface = points if rows is None else points[rows]
        clock("subset_s")
        advance()
        sigma = query_spread(surface, d.sigma_k)
        clock("sigma_s")
        queries = np.concatenate([gaussian_queries(surface, sigma, d.queries_per_point, rng),
                                  grid_queries(d.grid_queries, rng)])
        if d.drop_to_multiple > 0 and len(queries) % d.drop_to_multiple:
            queries = queries[: len(queries) - len(queries) % d.drop_to_multiple]
        clock("queries_s")
        advance()
        if d.anchors == "none":
            anchor_pts, anchor_tgt = np.zeros((0, 3)), np.zeros(0)
        else:
            anchor_pts, anchor_tgt = anchors(surface, d.anchors, d.anchor_resolution,
                                             d.anchor_squared_target, d.anchor_min_target)
        clock("anchors_s")
        advance()
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
        data = TrainingData(surface=as_t(surface), queries=as_t(queries), anchors=as_t(anchor_pts),
                            anchor_targets=as_t(anchor_tgt))
        if static_targets:
            data.set_nearest_targets()
            if cfg.loss.distance_target == "surface":
                own = planes if rows is None else planes.subset(rows)
                data.static_distance = as_t(
                    DataSurface.from_planes(surface, own, d.bridge, d.rim_reach, d.frame_bridge).distance(queries))
        clock("static_nn_s")
        advance()
    return data


class _StageClock:
    """Calling it with a name stores the seconds since the previous call (device-synchronised)."""

    def __init__(self, sink: dict[str, float] | None, device: torch.device) -> None:
        self.sink, self.device, self.last = sink, device, time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.sink is None:
            return
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        now = time.perf_counter()
        self.sink[name] = now - self.last
        self.last = now


def build_network(cfg: Config, seed: int, device: torch.device) -> torch.nn.Module:
    """The MLP of ``cfg.model``, initialised from ``seed`` on the CPU (identical on every device)."""
    gen = torch.Generator().manual_seed(seed)
    m = cfg.model
    net = DistanceMLP(model_widths(m), weight_norm=m.weight_norm, radius=m.geometric_init_radius,
                      abs_output=m.abs_output, generator=gen, skip=tuple(int(k) for k in m.skip))
    return net.to(device)


def fit(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
        progress: Progress = QUIET, planes: LocalPlanes | None = None,
        checkpoint: Checkpoint | None = None) -> Fitted:
    """Train the UltraBoneUDF field on a unit-space cloud (``planes``: the pipeline's local planes,
    for the ``surface`` distance target); returns the field and its counts."""
    t0 = time.perf_counter()
    stages: dict[str, float] = {}
    data = prepare(points, cfg, device, seed, progress, timings=stages, planes=planes)
    prep_s = time.perf_counter() - t0
    net = build_network(cfg, seed, device)
    loss_cfg, train_cfg = training_schedule(cfg.loss, cfg.train, device.type)
    result = train(net, data, loss_cfg, train_cfg, seed, progress, checkpoint=checkpoint)
    return fitted_field(net, data, prep_s, result, stages, loss_cfg, train_cfg)


def fit_many(clouds: list[np.ndarray], cfg: Config, device: torch.device, seed: int,
             progress: Progress = QUIET, planes: list[LocalPlanes | None] | None = None) -> list[Fitted]:
    """:func:`fit` for several unit-space clouds at once: each is prepared on its own, then their
    fields train together in one batched loop (:func:`~ultraboneudf.training.train_many`,
    equal step for step to separate runs); ``train_s`` is the batch's."""
    from ..training import train_many

    planes = planes if planes is not None else [None] * len(clouds)
    datas, prep, stages = [], [], []
    for points, own in zip(clouds, planes):
        t0 = time.perf_counter()
        stage: dict[str, float] = {}
        datas.append(prepare(points, cfg, device, seed, progress, timings=stage, planes=own))
        prep.append(time.perf_counter() - t0)
        stages.append(stage)
    nets = [build_network(cfg, seed, device) for _ in clouds]
    loss_cfg, train_cfg = training_schedule(cfg.loss, cfg.train, device.type)
    trained, results = train_many(nets, datas, loss_cfg, train_cfg, [seed] * len(clouds), progress)
    return [fitted_field(net, data, p, r, st, loss_cfg, train_cfg)
            for net, data, p, r, st in zip(trained, datas, prep, results, stages)]


def fitted_field(net: torch.nn.Module, data: TrainingData, prep_s: float, result: TrainResult,
                 stages: dict[str, float], loss_cfg: LossConfig, train_cfg: TrainConfig) -> Fitted:
    """The :class:`Fitted` of a trained network: its field, counts, timings and the schedule it
    trained with (``train.budget`` resolved: the sidecar's ``method_info``)."""
    counts = {"surface_points": len(data.surface), "queries": len(data.queries),
              "anchors": len(data.anchors), "parameters": count_parameters(net)}
    info = {"budget": train_cfg.budget, "iters": train_cfg.iters, "batch": train_cfg.batch, "lr": train_cfg.lr,
            "warmup": train_cfg.warmup, "gs_anchors": loss_cfg.gs_anchors, "os_rows": loss_cfg.os_rows,
            "train_step": result.step, "train_threads": result.threads}
    return Fitted(field=MLPField(net), counts=counts,
                  timings={"preprocess_s": prep_s, "train_s": result.seconds, **stages}, history=result.history,
                  info=info)
