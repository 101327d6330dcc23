"""The one map between millimetres and the unit space the fields live in (§0.1).

``x̂ = (x − c) / s`` with ``c`` the bounding-box centre and ``s`` the longest bounding-box side, so
the longest side spans [−0.5, 0.5]. Every unit-space threshold in the configs assumes this map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True)
class Normalizer:
    """Affine map mm → unit space: ``centre`` (3,) in mm and ``scale`` in mm per unit."""

    centre: np.ndarray
    scale: float

    @classmethod
    def fit(cls, points_mm: np.ndarray) -> "Normalizer":
        """The map of §0.1 for an ``(N, 3)`` cloud in mm."""
        lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
        scale = float((hi - lo).max())
        if not scale > 0:
            raise ValueError("cannot normalise a cloud of zero extent")
        return cls(centre=(hi + lo) / 2.0, scale=scale)

    def forward(self, points_mm: np.ndarray) -> np.ndarray:
        """mm → unit space, ``(N, 3)``."""
        return (np.asarray(points_mm, dtype=np.float64) - self.centre) / self.scale

    def inverse(self, points_unit: np.ndarray) -> np.ndarray:
        """Unit space → mm, ``(N, 3)``."""
        return np.asarray(points_unit, dtype=np.float64) * self.scale + self.centre

    def inverse_mesh(self, mesh: trimesh.Trimesh) -> trimesh.Trimesh:
        """A copy of a unit-space mesh with its vertices in mm (faces unchanged, no processing)."""
        return trimesh.Trimesh(self.inverse(mesh.vertices), np.asarray(mesh.faces), process=False)

    def to_dict(self) -> dict:
        return {"centre_mm": [float(v) for v in self.centre], "scale_mm": self.scale}
