"""What a registration gives: the CT → target transform (mm) and how well and how surely the CT
explains the ultrasound, with everything needed to repeat it."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from .._version import __version__
from ..io import save_json
from . import rigid

KIND = "ultraboneudf registration"
"""The ``kind`` of a registration's JSON, by which an output of this package is recognised."""


@dataclass
class Registration:
    """The rigid pose of a CT bone in the ultrasound (target) frame.

    ``transform`` ``(4, 4)``: maps CT coordinates (mm) to target coordinates (mm),
    ``x_target = R x_ct + t``. ``residual_mm``: root mean square distance from the target points the
    CT explains (within ``inlier_mm``) to the placed CT surface. ``overlap``: the share of the
    (thinned) target points within ``inlier_mm`` of the placed CT — how much of the ultrasound is
    bone of this CT. ``coverage``: the share of the CT surface within ``inlier_mm`` of a target
    point — how much of the bone the ultrasound saw. ``score``: the soft inlier share the poses are
    ranked by, ``mean(max(0, 1 − (d/inlier_mm)²))``. ``runner_up``: the best pose found that moves
    the CT surface by more than ``separation_mm`` (mean) from this one — its ``transform``, ``score``
    and that ``distance_mm`` — or ``None`` if every hypothesis refined into this pose.
    ``confidence``: ``1 − runner_up score / score`` (0: another pose explains the ultrasound as
    well, so the data cannot tell them apart; 1: nothing else comes close); ``None`` when the pose
    came from ``init`` without a search. ``weakest_motion``: the motion of the CT the explained
    points feel least (:func:`~.constraint.weakest_motion`): its ``sensitivity`` is the RMS change of
    their distances per mm it moves the CT surface — near 0 along a slide the view cannot fix, such
    as a long bone's shaft seen without its ends. ``timings`` in seconds.
    """

    transform: np.ndarray
    residual_mm: float
    overlap: float
    coverage: float
    score: float
    confidence: float | None
    runner_up: dict[str, Any] | None
    weakest_motion: dict[str, Any]
    inlier_mm: float
    hypotheses: int
    timings: dict[str, float]
    counts: dict[str, int]
    seed: int
    options: dict[str, Any]
    init: dict[str, Any] | None = None
    input: dict[str, Any] = field(default_factory=dict)
    version: str = __version__

    @property
    def inverse(self) -> np.ndarray:
        """``(4, 4)`` target → CT."""
        return rigid.invert(self.transform)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """CT points ``(N, 3)`` (mm) in the target frame."""
        return rigid.apply(self.transform, np.asarray(points, dtype=np.float64))

    def place(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """A copy of the CT ``mesh`` moved into the target frame."""
        return trimesh.Trimesh(self.apply(mesh.vertices), np.asarray(mesh.faces), process=False)

    def to_json(self) -> dict[str, Any]:
        """The JSON record (see ``docs/registration.md``)."""
        r = self.transform
        return {
            "kind": KIND,
            "transform": _matrix(r),
            "transform_target_to_ct": _matrix(self.inverse),
            "rotation_deg": round(float(rigid.rotation_angle_deg(r[:3, :3])), 4),
            "translation_mm": [round(float(v), 4) for v in r[:3, 3]],
            "residual_mm": _round(self.residual_mm),
            "inlier_mm": self.inlier_mm,
            "overlap": _round(self.overlap),
            "coverage": _round(self.coverage),
            "score": _round(self.score),
            "confidence": _round(self.confidence),
            "runner_up": None if self.runner_up is None else {
                "transform": _matrix(self.runner_up["transform"]),
                "score": _round(self.runner_up["score"]),
                "distance_mm": _round(self.runner_up["distance_mm"]),
            },
            "weakest_motion": self.weakest_motion,
            "hypotheses": self.hypotheses,
            "timings": {k: round(v, 4) for k, v in self.timings.items()},
            "counts": self.counts,
            "seed": self.seed,
            "options": self.options,
            "init": self.init,
            "version": self.version,
            "input": self.input,
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write :meth:`to_json` to ``path`` atomically."""
        save_json(self.to_json(), path)


def _matrix(m: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(m)]


def _round(v: float | None) -> float | None:
    return None if v is None else round(float(v), 5)
