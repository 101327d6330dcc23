"""The named presets: a :class:`Config` each, differing from the defaults only where the paper and
the official code disagree (§1.11) and in the ``fast`` and ``robust`` presets designed here."""

from __future__ import annotations

from typing import Any

from ..errors import InputError
from .sections import Config, DataConfig, ExtractConfig


# The DualMesh-UDF official driver values (§2.11): the generic defaults of the extractor.
DMU_DEFAULTS: dict[str, Any] = dict(
    max_depth=7, valid_threshold=0.002, min_udf=0.002, corner_factor=1.0, edge_factor=1.0,
    plane_factor=0.15, sv_threshold=0.08, dedup_eps=1e-7,
)


def _official() -> Config:
    return Config()


def _paper() -> Config:
    cfg = Config()
    cfg.data = DataConfig(subset="fps", max_points=40_000, grid_queries=0, drop_to_multiple=0,
                          anchors="bbox", anchor_squared_target=False, anchor_min_target=-1.0)
    cfg.loss.tangent_norm = "l2"
    cfg.loss.gs_form = "per_anchor"
    # 256 cells across the object (depth 9 on [−1, 1]³) with the official DMU thresholds (§1.11).
    cfg.extract = ExtractConfig(**{**DMU_DEFAULTS, "max_depth": 9})
    # Without grid queries the far field is free to overestimate; test the band from 0.125-unit cells.
    cfg.extract.band_start_depth = 4
    cfg.extract.mode = "clean"  # one-layer, edge-manifold mesh; "faithful" reproduces DMU
    cfg.extract.trim_mm = 3.0   # no surface > 3 mm from the data (README, "Support trim")
    cfg.clean.project_steps = 0  # see _fast
    return cfg


def _fast() -> Config:
    """Designed for a 100k-point cloud on a CPU (measured in docs/results.md).

    What limits a short run is the number of optimiser steps: the tangent loss grows the zero set
    outward from the initial sphere and can leave a part of the bone without one. A warm start
    (regressing u on the distance to P) first puts a zero set near every part of the data; the
    far-field term, applied to every query, keeps forbidding zero sets away from the data and pins u
    to the distance near it, so the zero set reaches the open rims. A 64-wide network is as accurate
    as 128 here at half the work; the epoch sampler and 128 random anchors a step for L_GS cut the
    per-step overhead.
    """
    cfg = Config()
    cfg.data.subset = "fps"
    cfg.data.max_points = 10_000
    cfg.data.queries_per_point = 20
    cfg.data.grid_queries = 10_000
    cfg.data.drop_to_multiple = 0
    cfg.model.hidden = (64, 64, 64, 64)
    cfg.model.geometric_init_radius = 0.1
    cfg.loss.gs_form = "per_anchor"
    cfg.loss.warm_start = 0.1
    cfg.loss.lambda_far = 1.0
    cfg.loss.far_threshold = 0.0
    cfg.loss.gs_anchors = 128
    cfg.train.iters = 10_000
    cfg.train.batch = 250
    cfg.train.sampler = "epoch"
    cfg.train.threads = 1
    cfg.train.warmup = 400
    cfg.train.lr = 2e-3
    cfg.train.budget = "auto"
    cfg.extract.max_depth = 8
    cfg.extract.mode = "clean"
    cfg.extract.trim_mm = 3.0
    # Trained fields' minima are not their exact zero sets: moving the QEF vertices onto them cost
    # accuracy on every field measured (docs/results.md, "Presets").
    cfg.clean.project_steps = 0
    return cfg


def _robust() -> Config:
    """``fast`` made for what ultrasound gives: noisy, slice-structured, gappy points with false echoes.

    A robust plane is fitted to the points within 4 mm of every point (mm, before normalisation;
    wider, up to 8 mm, where the median point has fewer than 36 points within 4 mm: a sparse
    cloud): points more than three robust spreads from it are dropped (false echoes in the shadow,
    isolated detections) and the rest are moved onto it (noise along the beam, offsets between
    slices). The warm start and the far-field term regress ``u`` on the distance to the surface
    interpolated between the points across gaps up to the plane's radius (across a sweep's frames,
    when they are known, up to 10 mm: a run of lost frames), instead of the distance to the nearest point, which
    between slices lies beside the query rather than under it; past the data's rims that surface
    goes on for half the plane radius (2 mm), where an oblique echo faded (not past a sweep's first
    and last image planes, past which the probe never looked), also past the few echoes of a steep
    face (planes 60–80° from the beam orient the surface there without moving the points, and keep
    them where they are too sparse for a plane at 4 mm). The support trim measures to the bridged
    surface, so bridged gaps stay closed, and also drops the faces 1 mm or more from it along its
    normal (sheets the noise band leaves under or over the bone; on a thinner band three times the
    points' spread about their planes, at least 0.4 mm) and, on a sweep, those 0.5 mm or more
    past its rims within the image planes (the field's continuation of a sheet where the bone curves
    away from the beam). ``L_OS`` on 256 surface points a
    step pins the zero level to the data where few frames saw the bone and the tangent phase alone
    leaves the field above zero there. Leaves are kept ≥ 0.75 mm, so a small bone is not meshed
    finer than its data resolve; the extractor's margin covers how far above zero the field stays on
    its own points, so where a thick, sparse band keeps it above zero between them (a compounded
    cloud's slices) the surface is still meshed; and the mesh's folds (faces meeting at more than
    60°, where the QEF vertices scatter across the noisy field's minimum) are smoothed out. The
    network is twice as wide as ``fast``'s (4 × 128): on these points it follows the denoised
    surface more closely, for 1.6–1.8× the time (docs/robustness.md measures each part); its step
    (634 rows through 128-wide layers) runs faster on two CPU threads than on one, ``fast``'s does
    not (docs/development.md)."""
    cfg = _fast()
    cfg.model.hidden = (128, 128, 128, 128)
    cfg.train.threads = 2
    cfg.data.max_voxels = 200_000
    cfg.data.surface_fit_mm = 4.0
    cfg.data.surface_fit_points = 36
    cfg.data.denoise = 1
    cfg.data.outlier_sigmas = 3.0
    cfg.data.bridge = 1.0
    cfg.data.frame_bridge = 2.5
    cfg.data.rim_reach = 0.5
    cfg.data.steep_planes_deg = 80.0
    cfg.data.front_echo_mm = 30.0
    cfg.data.beams_from_order = True
    cfg.data.min_component = 0.02
    cfg.loss.distance_target = "surface"
    cfg.loss.lambda_os = 10.0
    cfg.loss.os_rows = 256
    cfg.extract.min_leaf_mm = 0.75
    cfg.extract.data_margin = 1.25
    cfg.extract.trim_normal_mm = 1.0
    cfg.extract.trim_normal_sigmas = 3.0
    cfg.extract.trim_rim_mm = 0.5
    cfg.extract.trim_grazing_deg = 75.0
    cfg.clean.unfold_deg = 60.0
    return cfg


PRESETS = {"robust": _robust, "fast": _fast, "official": _official, "paper": _paper}

DEFAULT_PRESET = "robust"
"""What ``reconstruct`` uses unless told otherwise: the best result on ultrasound-like data on a CPU."""

PRESET_HELP = {
    "robust": "the default: noisy, gappy, slice-structured ultrasound points with false echoes",
    "fast": "robust without the noise handling: clean, dense clouds (e.g. sampled from a mesh)",
    "official": "the public reference code reproduced, deviations included (a GPU run)",
    "paper": "the paper's text where it differs from the code (a GPU run)",
}
"""One line per preset: which to use when (``--help`` and the README)."""


def preset(name: str) -> Config:
    """A fresh :class:`Config` of the named preset (``robust``, ``fast``, ``official`` or ``paper``)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None
