"""Evaluation as the paper does it (docs/ALGORITHMS.md §6.2, §6.3, §1.9): metrics, statistics, tables,
pictures. Everything is in millimetres.

Metrics (:mod:`.metrics`): area-uniform seeded sampling of both surfaces (5,000,000 points each by
default), optional pseudo ground truth (ground-truth samples within τ of the *raw* ultrasound
cloud; τ = 2 mm paper, 1 mm official code), directed Euclidean nearest-neighbour distances,
``CD = ½ (mean d_RG + mean d_GR)``, ``HD95 = max(P95 d_RG, P95 d_GR)`` (linear-interpolated
percentiles) with the two alternatives stored beside it. No mesh is a counted failure.

Statistics (:mod:`.stats`): paired two-sided Wilcoxon signed-rank tests of a baseline against each
competitor (pairing unit: the reconstruction; zero differences discarded), Bonferroni
``p_corr = min(1, k·p_raw)``; per-specimen means and the mean of the specimen means.

Tables (:mod:`.tables`), PNG renders (:mod:`.render`) and an offline interactive HTML viewer
(:mod:`.viewer`).
"""

from .metrics import (
    DEFAULT_SAMPLES,
    JSON_KEYS,
    OFFICIAL_PSEUDO_GT_MM,
    PAPER_PSEUDO_GT_MM,
    SHARE_KEYS,
    EvalResult,
    GroundTruth,
    chamfer_hd95,
    directed_distances,
    evaluate,
    metrics_from_distances,
    prepare_ground_truth,
    pseudo_gt_mask,
)
from ..geometry.neighbors import nearest_distances
from .render import (
    colormap,
    reference_points,
    render_distance_image,
    render_distance_png,
    render_grid_image,
    render_grid_png,
    vertex_distances,
)
from .sampling import DegenerateMeshError, sample_surface, surface_area
from .stats import (
    Comparison,
    Record,
    WilcoxonResult,
    bonferroni,
    compare_to_baseline,
    failure_counts,
    mean_of_specimen_means,
    read_results_csv,
    specimen_means,
    wilcoxon_signed_rank,
    write_results_csv,
)
from .tables import Table, comparisons_table, format_table, results_table
from .viewer import viewer_html, write_viewer

__all__ = [
    "evaluate", "EvalResult", "GroundTruth", "prepare_ground_truth", "metrics_from_distances",
    "chamfer_hd95", "directed_distances", "pseudo_gt_mask", "nearest_distances", "sample_surface",
    "surface_area", "DegenerateMeshError", "DEFAULT_SAMPLES", "PAPER_PSEUDO_GT_MM",
    "OFFICIAL_PSEUDO_GT_MM", "JSON_KEYS", "SHARE_KEYS",
    "Record", "WilcoxonResult", "Comparison", "wilcoxon_signed_rank", "bonferroni",
    "compare_to_baseline", "specimen_means", "mean_of_specimen_means", "failure_counts",
    "read_results_csv", "write_results_csv",
    "Table", "results_table", "comparisons_table", "format_table",
    "colormap", "vertex_distances", "reference_points", "render_distance_image",
    "render_distance_png", "render_grid_image", "render_grid_png", "viewer_html", "write_viewer",
]
