"""Surface-to-surface metrics as the paper computes them (docs/ALGORITHMS.md §6.2, §1.9). All in mm.

Conventions, stated once and used everywhere:

* ``S_R``: ``samples`` points drawn uniformly by area on the reconstruction; ``S_G``: ``samples``
  points drawn the same way on the ground-truth mesh (5,000,000 each by default, as the reference
  code). Sampling is seeded; the ground-truth draw depends only on ``seed``, so every method
  evaluated with the same seed meets the same ground-truth points.
* Pseudo ground truth (UltraBones100k): keep the points of ``S_G`` whose distance to the nearest
  point of the **raw** ultrasound cloud is ``≤ τ`` (``pseudo_gt_mm``; 2 mm in the paper, 1 mm in the
  official code). The sampled points are filtered, not the mesh. ``τ`` is always recorded.
* Directed distances, Euclidean (not squared): ``d_RG(x) = min_{y∈S_G} ‖x − y‖`` for ``x ∈ S_R``
  and ``d_GR(y) = min_{x∈S_R} ‖x − y‖`` for ``y ∈ S_G``.
* Chamfer distance ``CD = ½ (mean d_RG + mean d_GR)`` (mean of the two directed means).
* ``HD95 = max(P95(d_RG), P95(d_GR))``: the larger of the two directed 95th percentiles, with the
  percentile linearly interpolated between order statistics (NumPy's default ``"linear"`` method).
  The two alternatives of §6.2 are kept beside it: ``hd95_union_mm = P95(d_RG ∪ d_GR)`` and
  ``hd95_mean_mm = ½ (P95(d_RG) + P95(d_GR))``.
* Shares within a distance ``t`` (``within_mm``; asked for, not computed by default), as real data
  is scored against CT: ``on_gt`` = the share of the reconstruction's area within ``t`` of the
  *whole* ground-truth mesh (what the reconstruction invented lies farther), ``covered`` = the share
  of the (pseudo) ground truth within ``t`` of the reconstruction (what it missed lies farther):
  ``mean(d_RG' ≤ t)`` over ``S_R`` (``d_RG'`` measured to ``S_G`` before the pseudo-GT filter) and
  ``mean(d_GR ≤ t)``.
* A missing or empty reconstruction is a *failure*: :func:`evaluate` returns a result with
  ``failed=True``, the reason, and ``None`` for every metric, never a zero.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Optional, Union

import numpy as np

from ..errors import InputError
from ..geometry.neighbors import KDTree, grid_distances, kd_tree, spatially_sorted, surface_tree, tree_distances
from ..progress import QUIET, Progress
from .sampling import DegenerateMeshError, MeshLike, sample_surface, surface_area

DEFAULT_SAMPLES = 5_000_000
"""Points sampled on each surface, as the reference code (§1.9)."""
PAPER_PSEUDO_GT_MM = 2.0
"""Pseudo-ground-truth threshold τ of the paper [P]; the official code uses 1.0 mm [C]."""
OFFICIAL_PSEUDO_GT_MM = 1.0
PERCENTILE = 95.0

JSON_KEYS = ("cd_mm", "hd95_mm", "d_rg_mean_mm", "d_gr_mean_mm", "hd95_rg_mm", "hd95_gr_mm",
             "samples", "pseudo_gt_mm")
"""The keys of ``ultraboneudf evaluate --json`` (DESIGN.md), in this order."""
SHARE_KEYS = ("within_mm", "on_gt", "covered")
"""The keys ``evaluate --within-mm`` adds after :data:`JSON_KEYS`."""


# --------------------------------------------------------------------------------------------
# pure functions on distances and samples


def percentile95(d: np.ndarray) -> float:
    """Linear-interpolated 95th percentile of ``d`` (mm)."""
    return float(np.percentile(d, PERCENTILE, method="linear"))


def metrics_from_distances(d_rg: np.ndarray, d_gr: np.ndarray) -> dict[str, float]:
    """Chamfer and HD95 numbers (mm) from the two directed distance arrays.

    Returns ``cd_mm``, ``hd95_mm`` (max of directed P95), ``d_rg_mean_mm``, ``d_gr_mean_mm``,
    ``hd95_rg_mm``, ``hd95_gr_mm``, ``hd95_union_mm`` (P95 of both sets pooled) and
    ``hd95_mean_mm`` (mean of the directed P95).
    """
    d_rg = np.asarray(d_rg, dtype=np.float64).ravel()
    d_gr = np.asarray(d_gr, dtype=np.float64).ravel()
    if len(d_rg) == 0 or len(d_gr) == 0:
        raise ValueError("metrics_from_distances: both directed distance arrays must be non-empty")
    mean_rg, mean_gr = float(d_rg.mean()), float(d_gr.mean())
    p_rg, p_gr = percentile95(d_rg), percentile95(d_gr)
    return {
        "cd_mm": 0.5 * (mean_rg + mean_gr),
        "hd95_mm": max(p_rg, p_gr),
        "d_rg_mean_mm": mean_rg,
        "d_gr_mean_mm": mean_gr,
        "hd95_rg_mm": p_rg,
        "hd95_gr_mm": p_gr,
        "hd95_union_mm": percentile95(np.concatenate([d_rg, d_gr])),
        "hd95_mean_mm": 0.5 * (p_rg + p_gr),
    }


def directed_distances(source: np.ndarray, target: np.ndarray, workers: int = -1,
                       device: str = "cpu") -> np.ndarray:
    """``min_{y∈target} ‖x − y‖`` for every row ``x`` of ``source``; ``(len(source),)`` float64, mm."""
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if device == "cpu":
        return tree_distances(surface_tree(target), source, workers=workers)
    return grid_distances(source, target, device=device, workers=workers)


def chamfer_hd95(recon_samples: np.ndarray, gt_samples: np.ndarray, workers: int = -1,
                 device: str = "cpu") -> dict[str, float]:
    """:func:`metrics_from_distances` of two sample sets ``(N, 3)`` and ``(M, 3)`` in mm."""
    d_rg = directed_distances(recon_samples, gt_samples, workers, device)
    d_gr = directed_distances(gt_samples, recon_samples, workers, device)
    return metrics_from_distances(d_rg, d_gr)


def pseudo_gt_mask(gt_samples: np.ndarray, raw_points: np.ndarray, tau_mm: float,
                   workers: int = -1) -> np.ndarray:
    """Boolean ``(M,)``: which ground-truth samples lie within ``tau_mm`` (inclusive) of the raw cloud."""
    tau = float(tau_mm)
    if not (np.isfinite(tau) and tau >= 0):
        raise InputError(f"pseudo-GT threshold: must be a finite number ≥ 0 mm, got {tau_mm}")
    tree = kd_tree(np.asarray(raw_points, dtype=np.float64))
    gt_samples = np.asarray(gt_samples, dtype=np.float64)
    # the search stops at the bound; a hair above τ keeps points at exactly τ (≤ τ, not < τ)
    d, _ = tree.query(gt_samples, k=1, distance_upper_bound=np.nextafter(tau, np.inf), workers=workers)
    return d <= tau


# --------------------------------------------------------------------------------------------
# the ground truth, prepared once and reused for every method of a scan


def _rng(seed: int, stream: int) -> np.random.Generator:
    """Independent generator per (seed, stream): stream 0 = reconstruction, 1 = ground truth."""
    return np.random.default_rng([int(seed), stream])


@dataclass
class GroundTruth:
    """Ground-truth samples ready for distance queries (after the pseudo-GT filter, if any).

    ``points`` ``(M, 3)`` mm, spatially ordered; ``drawn`` samples were drawn on the mesh before
    filtering; ``pseudo_gt_mm`` is τ or ``None`` when the whole ground truth is used; ``whole``
    ``(drawn, 3)`` the samples before the filter, kept where asked for (the share of a
    reconstruction on the ground truth measures to them), else ``None``.
    """

    points: np.ndarray
    drawn: int
    pseudo_gt_mm: Optional[float]
    seed: int
    whole: Optional[np.ndarray] = field(default=None, repr=False)
    _tree: Optional[KDTree] = field(default=None, repr=False)
    _whole_tree: Optional[KDTree] = field(default=None, repr=False)

    @property
    def tree(self) -> KDTree:
        if self._tree is None:
            self._tree = surface_tree(self.points)
        return self._tree

    @property
    def whole_tree(self) -> KDTree:
        """A tree of :attr:`whole` (which must have been kept)."""
        if self._whole_tree is None:
            self._whole_tree = surface_tree(self.whole)
        return self._whole_tree


def prepare_ground_truth(gt: MeshLike, raw_points: Optional[np.ndarray] = None,
                         pseudo_gt_mm: Optional[float] = None, samples: int = DEFAULT_SAMPLES,
                         seed: int = 0, workers: int = -1, source: str = "ground truth",
                         keep_whole: bool = False) -> GroundTruth:
    """Sample the ground-truth mesh and apply the pseudo-GT filter (§6.2 steps 2–3).

    ``raw_points`` is the raw (not down-sampled) ultrasound cloud ``(K, 3)`` in mm; when given, τ
    defaults to :data:`PAPER_PSEUDO_GT_MM`. Giving ``pseudo_gt_mm`` without ``raw_points`` is an
    error. ``keep_whole``: also keep the samples before the filter (``GroundTruth.whole``, needed
    by :func:`evaluate`'s ``within_mm``; as much memory again). Raises :class:`InputError` naming
    ``source`` for a mesh with no area or when no sample survives the filter.
    """
    if pseudo_gt_mm is not None and raw_points is None:
        raise InputError("pseudo-GT threshold given without the raw ultrasound points to filter by")
    if raw_points is not None and pseudo_gt_mm is None:
        pseudo_gt_mm = PAPER_PSEUDO_GT_MM
    points = sample_surface(gt, samples, _rng(seed, 1), source=source)
    whole = None
    if raw_points is not None:
        raw = np.asarray(raw_points, dtype=np.float64)
        if raw.ndim != 2 or raw.shape[1] < 3 or len(raw) == 0:
            raise InputError(f"raw ultrasound points: expected a non-empty N×3 array, got shape {raw.shape}")
        keep = pseudo_gt_mask(points, raw[:, :3], float(pseudo_gt_mm), workers)
        if not keep.any():
            raise InputError(f"{source}: no ground-truth sample lies within {pseudo_gt_mm} mm of the "
                             f"ultrasound points; are both in the same frame and in mm?")
        if keep_whole:
            whole = spatially_sorted(points)
        points = points[keep]
    return GroundTruth(points=spatially_sorted(points), drawn=int(samples),
                       pseudo_gt_mm=None if pseudo_gt_mm is None else float(pseudo_gt_mm), seed=int(seed),
                       whole=whole)


# --------------------------------------------------------------------------------------------
# the result and the one-call evaluation


@dataclass(frozen=True)
class EvalResult:
    """Metrics of one reconstruction against its ground truth (mm); see the module docstring.

    ``failed`` is true when there was no usable mesh; then every metric is ``None`` and ``reason``
    says why. ``samples`` is the number drawn on each surface; ``samples_gt`` the ground-truth
    samples kept by the pseudo-GT filter; ``timings`` are seconds per stage. ``within_mm``,
    ``on_gt`` and ``covered``: the shares of the module docstring, ``None`` unless asked for.
    """

    failed: bool
    reason: Optional[str]
    cd_mm: Optional[float]
    hd95_mm: Optional[float]
    d_rg_mean_mm: Optional[float]
    d_gr_mean_mm: Optional[float]
    hd95_rg_mm: Optional[float]
    hd95_gr_mm: Optional[float]
    hd95_union_mm: Optional[float]
    hd95_mean_mm: Optional[float]
    samples: int
    samples_recon: int
    samples_gt: int
    pseudo_gt_mm: Optional[float]
    seed: int
    device: str = "cpu"
    timings: dict[str, float] = field(default_factory=dict)
    within_mm: Optional[float] = None
    on_gt: Optional[float] = None
    covered: Optional[float] = None

    def to_json(self) -> dict[str, Any]:
        """Exactly the keys of ``evaluate --json`` (:data:`JSON_KEYS`), then :data:`SHARE_KEYS`
        where the shares were asked for; metrics are ``null`` on failure."""
        full = asdict(self)
        keys = JSON_KEYS + (SHARE_KEYS if self.within_mm is not None else ())
        return {key: full[key] for key in keys}

    def to_dict(self) -> dict[str, Any]:
        """Every field, JSON-serialisable."""
        return asdict(self)


def _failure(reason: str, gt: GroundTruth, samples: int, device: str,
             timings: dict[str, float], within_mm: Optional[float]) -> EvalResult:
    none = dict.fromkeys(("cd_mm", "hd95_mm", "d_rg_mean_mm", "d_gr_mean_mm", "hd95_rg_mm",
                          "hd95_gr_mm", "hd95_union_mm", "hd95_mean_mm"))
    return EvalResult(failed=True, reason=reason, samples=int(samples), samples_recon=0,
                      samples_gt=len(gt.points), pseudo_gt_mm=gt.pseudo_gt_mm, seed=gt.seed,
                      device=device, timings=timings, within_mm=within_mm, **none)


def evaluate(recon: Optional[MeshLike], gt: Union[MeshLike, GroundTruth],
             raw_points: Optional[np.ndarray] = None, pseudo_gt_mm: Optional[float] = None,
             samples: int = DEFAULT_SAMPLES, seed: int = 0, workers: int = -1,
             device: str = "cpu", progress: Progress = QUIET, gt_source: str = "ground truth",
             within_mm: Optional[float] = None) -> EvalResult:
    """Chamfer distance and HD95 (mm) of a reconstruction against a ground-truth mesh (§6.2).

    Parameters
    ----------
    recon:
        The reconstructed mesh in mm (``trimesh.Trimesh`` or ``(vertices, faces)``), or ``None``
        when the method produced nothing. ``None``, no faces or zero area give ``failed=True``.
    gt:
        The ground-truth mesh in mm, or a :class:`GroundTruth` from :func:`prepare_ground_truth`
        (then ``raw_points``/``pseudo_gt_mm`` must not be given again; its sample count is used).
    raw_points:
        Raw ultrasound cloud ``(K, 3)`` in mm for the pseudo ground truth; τ defaults to 2 mm.
    pseudo_gt_mm:
        τ in mm (2 = paper, 1 = official code). Requires ``raw_points``.
    samples:
        Points drawn on each surface (default 5,000,000).
    seed:
        Seed of both samplings; same inputs and seed give the same numbers.
    workers:
        Threads of the KD-tree queries (``-1``: all cores).
    device:
        ``"cpu"`` (KD-tree), ``"cuda"`` (grid search on the GPU) or ``"auto"``.
    gt_source:
        Name of the ground truth in error messages (e.g. its file).
    within_mm:
        ``t`` in mm: also the shares ``on_gt`` and ``covered`` (module docstring). With a prepared,
        filtered :class:`GroundTruth` it must have been prepared with ``keep_whole=True``.
    """
    from ..devices import resolve_device  # torch only when evaluating

    device = str(resolve_device(device))
    if within_mm is not None:
        within_mm = float(within_mm)
        if not (np.isfinite(within_mm) and within_mm >= 0):
            raise InputError(f"share distance: must be a finite number ≥ 0 mm, got {within_mm}")
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    if isinstance(gt, GroundTruth):
        if raw_points is not None or pseudo_gt_mm is not None:
            raise InputError("pass raw_points/pseudo_gt_mm to prepare_ground_truth, not with a prepared GroundTruth")
        truth = gt
        samples = truth.drawn
        if within_mm is not None and truth.pseudo_gt_mm is not None and truth.whole is None:
            raise InputError("the shares within a distance measure to the whole ground truth: prepare it "
                             "with prepare_ground_truth(..., keep_whole=True)")
    else:
        with progress.stage("ground truth"):
            truth = prepare_ground_truth(gt, raw_points, pseudo_gt_mm, samples, seed, workers, source=gt_source,
                                         keep_whole=within_mm is not None)
        timings["ground_truth_s"] = time.perf_counter() - t0
    if recon is None:
        return _failure("no mesh", truth, samples, device, timings, within_mm)
    try:
        area = surface_area(recon, "reconstruction")
    except InputError as exc:
        return _failure(str(exc), truth, samples, device, timings, within_mm)
    if not area > 0:
        return _failure("reconstruction: the mesh has no faces or zero area", truth, samples, device, timings,
                        within_mm)
    t1 = time.perf_counter()
    with progress.stage("sampling"):
        try:
            s_r = spatially_sorted(sample_surface(recon, samples, _rng(truth.seed, 0), source="reconstruction"))
        except DegenerateMeshError as exc:
            return _failure(str(exc), truth, samples, device, timings, within_mm)
    timings["sample_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    with progress.stage("distances", len(s_r) + len(truth.points)) as advance:
        if device == "cpu":
            d_rg = tree_distances(truth.tree, s_r, workers=workers, presorted=True, advance=advance)
            d_gr = tree_distances(surface_tree(s_r), truth.points, workers=workers, presorted=True,
                                  advance=advance)
        else:
            d_rg = grid_distances(s_r, truth.points, device=device, workers=workers)
            advance(len(s_r))
            d_gr = grid_distances(truth.points, s_r, device=device, workers=workers)
        shares: dict[str, float] = {}
        if within_mm is not None:
            if truth.pseudo_gt_mm is None:
                d_whole = d_rg  # nothing was filtered out
            elif device == "cpu":
                d_whole = tree_distances(truth.whole_tree, s_r, workers=workers, presorted=True)
            else:
                d_whole = grid_distances(s_r, truth.whole, device=device, workers=workers)
            shares = {"within_mm": within_mm, "on_gt": float(np.mean(d_whole <= within_mm)),
                      "covered": float(np.mean(d_gr <= within_mm))}
    timings["distance_s"] = time.perf_counter() - t2
    numbers = metrics_from_distances(d_rg, d_gr)
    timings["total_s"] = time.perf_counter() - t0
    return EvalResult(failed=False, reason=None, samples=int(samples), samples_recon=len(s_r),
                      samples_gt=len(truth.points), pseudo_gt_mm=truth.pseudo_gt_mm, seed=truth.seed,
                      device=device, timings=timings, **numbers, **shares)
