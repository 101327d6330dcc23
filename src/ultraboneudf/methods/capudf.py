"""CAP-UDF (§3): consistency-aware field loss, two-stage progressive schedule, pseudo-sign per-cell
marching cubes.

Input [I, §3.6]: the same pre-processed cloud as UltraBoneUDF (the preset's surface subset rule),
already in unit space; CAP-UDF's own re-normalisation is skipped because the subset's bounding box
is the cloud's up to FPS rounding.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import nn

from ..config import Config
from ..errors import InputError
from ..fields.base import normalize
from ..fields.mlp import MLPField, count_parameters, value_and_grad
from ..geometry.neighbors import NearestIndex
from ..geometry.queries import query_spread, surface_subset
from ..checkpoints import Checkpoint
from ..progress import QUIET, Progress
from ..training import Expansion, StridedSampler, TrainingData, train
from .base import Fitted
from .ultraboneudf import build_network

MIN_POINTS = 60


def configure(cfg: Config) -> None:
    """CAP-UDF ``base.conf`` defaults (§3.2–3.5). With any ``train.budget`` but ``reference`` the
    preset's iterations and batch are kept and the expansion happens after two thirds of them (the
    reference ratio 40k / 60k)."""
    cfg.model.hidden = (256,) * 8
    cfg.model.skip = (4,)
    cfg.model.abs_output = True
    cfg.loss.kind = "capudf"
    cfg.loss.lambda_gs = 0.0
    cfg.loss.lambda_os = 0.0
    cfg.data.queries = "capudf"
    cfg.data.anchors = "none"
    cfg.data.grid_queries = 0
    if cfg.train.budget != "reference":
        cfg.capudf.expand_at = (2 * cfg.train.iters) // 3
        cfg.capudf.expand_batch = 4 * cfg.train.batch
        cfg.capudf.expand_candidates = 200_000
        cfg.grid.resolution = 128
    else:
        cfg.train.iters = 60_000
        cfg.train.batch = 5_000
        cfg.train.lr = 1e-3
        cfg.train.warmup = 1_000
        cfg.capudf.expand_at = 40_000
        cfg.capudf.expand_batch = 20_000
        cfg.grid.resolution = 256
    cfg.extract.mode = "capudf_mc"
    cfg.grid.box = "surface"
    cfg.grid.box_margin = 0.05
    cfg.grid.cell_threshold = 0.005
    cfg.grid.far = -1.0
    cfg.extract.batch = 1_000_000


def capudf_samples(surface: np.ndarray, total: int, sigma_k: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """CAP-UDF data (§3.1 steps 2–5): a random subset of ``60·⌊N₀/60⌋`` rows ``P`` (shuffled) and the
    queries ``q = p + κ·σ(p)·ε`` in ``⌊total/N⌋`` rounds of one per point, ``κ = max(0.25, 0.25√(N/20k))``.
    Returns ``P`` (N, 3) and the queries (T, 3), stored round after round."""
    n = MIN_POINTS * (len(surface) // MIN_POINTS)
    if n == 0:
        raise InputError(f"CAP-UDF needs at least {MIN_POINTS} surface points, got {len(surface)}")
    p = surface[rng.permutation(len(surface))[:n]]
    sigma = query_spread(p, sigma_k)
    kappa = max(0.25, 0.25 * math.sqrt(n / 20_000))
    rounds = max(1, total // n)  # guard: N > total would give no queries (§3.6)
    eps = rng.standard_normal((rounds, n, 3))
    queries = (p[None] + kappa * sigma[None, :, None] * eps).reshape(-1, 3)
    return p, queries


def even_subsample(points: np.ndarray, count: int) -> np.ndarray:
    """About ``count`` evenly spread rows of ``points`` (M, 3): one point per occupied cell of a cubic
    grid whose edge is bisected until the occupied-cell count is within 2 % of ``count`` [I: stands in
    for the reference's Poisson-disk sampling, which also only approximates the count]."""
    if count <= 0:
        return points[:0]
    if len(points) <= count:
        return points
    lo = points.min(axis=0)
    h_small, h_big = 0.0, float((points.max(axis=0) - lo).max()) + 1e-12
    keep = np.arange(min(count, len(points)))
    for _ in range(50):
        h = 0.5 * (h_small + h_big)
        keys = np.floor((points - lo) / h).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        keep = np.sort(first)
        if abs(len(keep) - count) <= 0.02 * count:
            break
        if len(keep) > count:
            h_small = h
        else:
            h_big = h
    return points[keep]


def make_expansion(cfg: Config, seed: int) -> tuple[Expansion, dict[str, int]]:
    """The progressive expansion of §3.4 for :func:`~ultraboneudf.training.train`: generate candidate
    surface points by moving perturbed targets onto the field, keep the near-surface, non-outlier
    ones, add an evenly spread ``expand_rate·N`` of them to ``P`` and return the queries' new targets
    in ``P_dense``. The dict returned beside it records ``candidates`` and ``added`` points once the
    expansion has run."""
    tc = cfg.capudf
    stats: dict[str, int] = {}

    def expand(net: nn.Module, data: TrainingData) -> torch.Tensor:
        device = data.queries.device
        gen = torch.Generator(device=device).manual_seed(seed + 40_000)
        sampler = StridedSampler(len(data.queries), cfg.train.batch, gen, device)
        found: list[torch.Tensor] = []
        count, rounds = 0, 0
        max_rounds = 4 * math.ceil(tc.expand_candidates / max(1, sampler.batch)) + 10
        while count < tc.expand_candidates and rounds < max_rounds:
            rounds += 1
            b = sampler()
            t, q = data.static_targets[b], data.queries[b]
            std = (q - t).std()  # unbiased, over all 3K components
            cand = t + torch.randn(t.shape, generator=gen, device=device, dtype=t.dtype) * (tc.expand_low_range * std)
            with torch.enable_grad():
                u, g = value_and_grad(net, cand, create_graph=False)
            moved = (cand - u[:, None] * normalize(g)).detach()
            keep = u.detach() < tc.expand_df_filter
            found.append(moved[keep])
            count += int(keep.sum())
        stats["candidates"] = count
        stats["added"] = 0
        if not count:
            return data.static_targets  # no candidates: keep stage-1 targets
        cand = torch.cat(found)[: tc.expand_candidates]
        p = data.surface
        dist = (cand - p[NearestIndex(p).query(cand).to(device)]).norm(dim=1)
        cand = cand[dist < tc.expand_outlier].double().cpu().numpy()
        chosen = even_subsample(cand, int(round(tc.expand_rate * len(p))))
        stats["added"] = len(chosen)
        dense = torch.cat([p, torch.as_tensor(chosen, dtype=p.dtype, device=device)])
        return dense[NearestIndex(dense).query(data.queries).to(device)]

    return Expansion(at=tc.expand_at, batch=tc.expand_batch, targets=expand), stats


def fit(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
        progress: Progress = QUIET, checkpoint: Checkpoint | None = None) -> Fitted:
    """Train CAP-UDF on a unit-space cloud; returns the UDF field and the surface rows ``P`` (for the
    extraction box and the ``far`` trimming)."""
    d = cfg.data
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    with progress.stage("sampling", 2) as advance:
        surface = surface_subset(points, d.subset, d.subset_threshold, d.fps_sizes, d.max_points,
                                 device=str(device))
        p, queries = capudf_samples(surface, cfg.capudf.total_queries, d.sigma_k, rng)
        advance()
        as_t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
        data = TrainingData(surface=as_t(p), queries=as_t(queries), anchors=as_t(np.zeros((0, 3))),
                            anchor_targets=as_t(np.zeros(0)))
        data.set_nearest_targets()
        advance()
    prep_s = time.perf_counter() - t0
    net = build_network(cfg, seed, device)
    if 0 < cfg.capudf.expand_at >= cfg.train.iters:
        progress.log(f"capudf: capudf.expand_at={cfg.capudf.expand_at} ≥ train.iters={cfg.train.iters}; "
                     "one stage only (no progressive expansion)")
    expansion, stats = make_expansion(cfg, seed)
    result = train(net, data, cfg.loss, cfg.train, seed, progress, expansion=expansion, checkpoint=checkpoint)
    counts = {"surface_points": len(p), "queries": len(queries), "anchors": 0,
              "parameters": count_parameters(net), "expanded_points": stats.get("added", 0)}
    return Fitted(field=MLPField(net), counts=counts, timings={"preprocess_s": prep_s, "train_s": result.seconds},
                  history=result.history, surface=p, info={"train_step": result.step})
