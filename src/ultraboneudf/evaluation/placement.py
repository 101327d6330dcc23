"""Whether what is scored against a ground truth lies in its frame and unit.

A reconstruction, a ground-truth mesh and an ultrasound cloud whose bounding boxes lie apart, or
differ in size a hundredfold, were written in different frames or units: every distance between
them is then meaningless, and the scores say so only by being absurd. Said before the scoring,
which takes minutes on large meshes."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

UNIT_RATIO = 100.0
"""Sizes this many times apart are another unit: mm against m is 1,000, against cm 10, while a
short scan of a long bone (a 30 mm patch against a 450 mm femur) lies within a few tens."""


def _box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return pts.min(axis=0), pts.max(axis=0)


def placement_warnings(reference: tuple[str, np.ndarray], others: Sequence[tuple[str, np.ndarray]]
                       ) -> list[str]:
    """One sentence for each of ``others`` (``(name, points (N, 3) mm)``, e.g. a mesh's vertices)
    that differs from ``reference`` (the ground truth, the same form) in size by
    :data:`UNIT_RATIO` or more, or whose bounding box does not meet the reference's; ``[]`` when
    all of them overlap it."""
    ref_name, ref_points = reference
    ref_lo, ref_hi = _box(ref_points)
    ref_size = float(np.linalg.norm(ref_hi - ref_lo))
    out = []
    for name, points in others:
        if len(points) == 0:
            continue
        lo, hi = _box(points)
        size = float(np.linalg.norm(hi - lo))
        ratio = max(size, ref_size) / max(min(size, ref_size), 1e-12)
        gap = float(np.linalg.norm(np.maximum(0.0, np.maximum(lo - ref_hi, ref_lo - hi))))
        if ratio >= UNIT_RATIO:
            out.append(f"{name} spans {size:.3g} mm and {ref_name} {ref_size:.3g} mm ({ratio:,.0f}× apart): "
                       f"are both in mm?")
        elif gap > 0:
            out.append(f"{name} and {ref_name} do not overlap (their bounding boxes lie {gap:.3g} mm apart): "
                       f"are they in the same frame? (`ultraboneudf register {ref_name} SCAN -o T.json` "
                       f"places it on the ultrasound points; `--gt-pose T.json` applies it)")
    return out
