"""CarotidUDF (§5, inferred) and the Table 8 ablation variants (§5.5).

All three train an MLP UDF with the static pull loss ``L_pull`` on the UltraBoneUDF data pipeline and
differ in network and extraction:

| method | network | extraction |
| --- | --- | --- |
| ``carotidudf`` | ``[3, 256×8, 1]``, no skip (463,874 parameters) | UDF→SDF + marching cubes (§5.4) |
| ``vanilla_udf`` | UltraBoneUDF (191,042) | UDF→SDF + marching cubes |
| ``ultraboneudf_pull`` | UltraBoneUDF | DualMesh-UDF as the preset |

``L_GS`` is not added (§5.5 default). The fit also returns the surface rows and their oriented
normals (§1.2 steps 4, 6), which the ``normal-sign`` conversion needs.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ..config import Config
from ..fields.mlp import MLPField, count_parameters
from ..geometry.normals import ultraboneudf_normals
from ..geometry.surface_fit import LocalPlanes
from ..checkpoints import Checkpoint
from ..progress import QUIET, Progress
from ..training import train
from .base import Fitted
from .ultraboneudf import build_network, prepare


def _pull_only(cfg: Config) -> None:
    """``L_pull`` (Eq. 3, squared) alone: no L_GS, no L_OS, no anchors (§5.3, §5.5)."""
    cfg.loss.kind = "pull"
    cfg.loss.pull_norm = "squared"
    cfg.loss.lambda_gs = 0.0
    cfg.loss.lambda_os = 0.0
    cfg.data.anchors = "none"


def _udf2sdf_extraction(cfg: Config) -> None:
    """§5.4: ``normal-sign`` marching cubes on 256³ points over [−1, 1]³ (128³ with any
    ``train.budget`` but ``reference``)."""
    cfg.extract.mode = "udf2sdf"
    cfg.grid.udf2sdf = "normal-sign"
    cfg.grid.resolution = 256 if cfg.train.budget == "reference" else 128
    cfg.grid.box = "domain"
    cfg.extract.domain = (-1.0, 1.0)
    cfg.extract.batch = 1_000_000


def configure_carotidudf(cfg: Config) -> None:
    """CarotidUDF defaults (§5.2–5.4); iterations and batch stay the preset's (30,000 × 5,000)."""
    _pull_only(cfg)
    cfg.model.hidden = (256,) * 8
    cfg.model.skip = ()
    _udf2sdf_extraction(cfg)


def configure_vanilla(cfg: Config) -> None:
    """Vanilla UDF (§5.5): UltraBoneUDF network, ``L_pull``, CarotidUDF extraction."""
    _pull_only(cfg)
    _udf2sdf_extraction(cfg)


def configure_pull(cfg: Config) -> None:
    """UltraBoneUDF(L_pull) (§5.5): UltraBoneUDF network and extraction, ``L_pull`` only."""
    _pull_only(cfg)


def fit(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
        progress: Progress = QUIET, planes: LocalPlanes | None = None,
        checkpoint: Checkpoint | None = None) -> Fitted:
    """Train the pull-loss UDF on a unit-space cloud (``planes``: the pipeline's local planes, for
    the ``surface`` distance target of the warm start); returns the field, the surface rows and their
    oriented normals: the hints the ``udf2sdf`` extractor's ``normal-sign`` conversion needs, given
    whatever extractor the configuration names, so that the fit never depends on the extraction."""
    t0 = time.perf_counter()
    data = prepare(points, cfg, device, seed, progress, planes=planes)
    surface = data.surface.detach().double().cpu().numpy()
    normals = ultraboneudf_normals(surface, points)
    prep_s = time.perf_counter() - t0
    net = build_network(cfg, seed, device)
    result = train(net, data, cfg.loss, cfg.train, seed, progress, checkpoint=checkpoint)
    counts = {"surface_points": len(data.surface), "queries": len(data.queries),
              "anchors": len(data.anchors), "parameters": count_parameters(net)}
    return Fitted(field=MLPField(net), counts=counts, timings={"preprocess_s": prep_s, "train_s": result.seconds},
                  history=result.history, surface=surface, normals=normals, info={"train_step": result.step})
