"""FUNSR (§4): a neural *signed* distance field trained with the un-squared pull loss, the
sign-consistency constraint and a least-squares adversarial on-surface loss against a scalar
discriminator; meshed by marching cubes of the SDF on [−1, 1]³.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import nn

from ..config import Config
from ..fields.base import normalize
from ..fields.mlp import MLPField, count_parameters, value_and_grad
from ..geometry.surface_fit import LocalPlanes
from ..training.losses import lsgan_discriminator_loss, lsgan_generator_loss, pull_loss, sign_consistency_loss
from ..progress import QUIET, Progress
from ..training import LoopLog, StridedSampler, cpu_threads, flush_denormals, learning_rate
from .base import Fitted
from .ultraboneudf import build_network, prepare


class Discriminator(nn.Module):
    """FUNSR's discriminator (§4.2): scalar → 256 → 256 → 256 → scalar, LeakyReLU(0.2) after the first
    three layers, sigmoid output, no weight norm; 132,353 parameters. Input ``(K,)`` SDF values,
    output ``(K,)`` probabilities."""

    def __init__(self, width: int = 256, generator: torch.Generator | None = None) -> None:
        super().__init__()
        dims = [1, width, width, width, 1]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        with torch.no_grad():
            for i, layer in enumerate(self.layers):
                if i < len(self.layers) - 1:
                    layer.weight.copy_(torch.normal(0.0, math.sqrt(2.0) / math.sqrt(layer.out_features),
                                                    layer.weight.shape, generator=generator))
                else:
                    layer.weight.copy_(torch.normal(math.sqrt(math.pi), 1e-4, layer.weight.shape,
                                                    generator=generator))
                layer.bias.fill_(-0.5)

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        h = s[:, None]
        for i, layer in enumerate(self.layers):
            h = layer(h)
            h = torch.nn.functional.leaky_relu(h, 0.2) if i < len(self.layers) - 1 else torch.sigmoid(h)
        return h.squeeze(-1)


def configure(cfg: Config) -> None:
    """FUNSR defaults (§4.1–4.5): no voxel down-sampling, the UltraBoneUDF subset and queries (all
    stored queries kept), SDF network ``[3, 256×8, 1]`` with skip at layer 4 and no absolute value,
    un-squared pull + 0.005·SCC + 0.005·ADL, 15,000 iterations, SDF marching cubes on 256³ over [−1, 1]³.
    With any ``train.budget`` but ``reference`` the preset's iterations and batch stay and the mesh is 128³."""
    cfg.data.voxel_size_mm = 0.0
    cfg.data.anchors = "none"
    cfg.data.drop_to_multiple = 0
    cfg.model.hidden = (256,) * 8
    cfg.model.skip = (4,)
    cfg.model.abs_output = False
    cfg.loss.kind = "pull"
    cfg.loss.pull_norm = "unsquared"
    cfg.loss.lambda_gs = 0.0
    cfg.loss.lambda_os = 0.0
    cfg.funsr.lambda_scc = 0.005
    cfg.funsr.lambda_adl = 0.005
    cfg.funsr.disc_lr = 1e-3
    if cfg.train.budget == "reference":
        cfg.train.iters = 15_000
        cfg.train.batch = 5_000
        cfg.train.lr = 1e-3
        cfg.train.warmup = 1_000
    cfg.extract.mode = "sdf_mc"
    cfg.grid.resolution = 256 if cfg.train.budget == "reference" else 128
    cfg.grid.box = "domain"
    cfg.extract.domain = (-1.0, 1.0)
    cfg.extract.batch = 1_000_000


def fit(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
        progress: Progress = QUIET, log_every: int = 100, planes: LocalPlanes | None = None) -> Fitted:
    """Train FUNSR on a unit-space cloud (iteration order of §4.4; ``planes``: the pipeline's local
    planes, which the shared sampling needs for the ``surface`` distance target); returns the SDF
    field."""
    t0 = time.perf_counter()
    data = prepare(points, cfg, device, seed, progress, static_targets=True, planes=planes)
    prep_s = time.perf_counter() - t0
    net = build_network(cfg, seed, device)
    disc = Discriminator(generator=torch.Generator().manual_seed(seed + 1)).to(device)
    generator = torch.Generator(device=device).manual_seed(seed)
    sampler = StridedSampler(len(data.queries), cfg.train.batch, generator, device)
    opt = torch.optim.Adam(net.parameters(), lr=0.0, betas=(0.9, 0.999), eps=1e-8)
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.funsr.disc_lr, betas=(0.9, 0.999), eps=1e-8)
    lc, iters = cfg.loss, cfg.train.iters
    net.train()
    if device.type == "cuda":
        progress.log("training: eager steps (FUNSR's own loop, with its discriminator, is not captured)")
    # the discriminator's sigmoid saturates, and about 40% of its Adam second moments sink below
    # float32's normal range within 150 steps: unflushed, a CPU step takes 8 times as long
    with cpu_threads(cfg.train.threads), flush_denormals(device), progress.stage("training", iters) as advance:
        log = LoopLog(iters, advance, device, log_every, lr=cfg.train.lr, progress=progress)
        for i in range(iters):
            for group in opt.param_groups:
                group["lr"] = learning_rate(i, cfg.train.lr, cfg.train.warmup, iters)
            batch = sampler()
            opt.zero_grad(set_to_none=True)
            q, t = data.queries[batch], data.static_targets[batch]
            s, g = value_and_grad(net, q, create_graph=True)
            g_hat = normalize(g)
            moved = q - s[:, None] * g_hat
            terms = {"pull": pull_loss(moved, t, lc.pull_norm), "scc": sign_consistency_loss(g_hat, moved, t)}
            # discriminator step first: real samples are zeros, fake ones the detached SDF values
            opt_d.zero_grad(set_to_none=True)
            terms["disc"] = lsgan_discriminator_loss(disc(torch.zeros_like(s)), disc(s.detach()))
            terms["disc"].backward()
            opt_d.step()
            # generator term with the just-updated discriminator (its gradients are cleared next step)
            terms["adl"] = lsgan_generator_loss(disc(s))
            terms["total"] = terms["pull"] + cfg.funsr.lambda_scc * terms["scc"] + cfg.funsr.lambda_adl * terms["adl"]
            terms["total"].backward()
            opt.step()
            log.step(i, terms)
    train_s, hist = log.finish()
    net.eval()
    counts = {"surface_points": len(data.surface), "queries": len(data.queries), "anchors": 0,
              "parameters": count_parameters(net), "discriminator_parameters": count_parameters(disc)}
    return Fitted(field=MLPField(net), counts=counts, timings={"preprocess_s": prep_s, "train_s": train_s},
                  history=hist, surface=data.surface.detach().double().cpu().numpy())
