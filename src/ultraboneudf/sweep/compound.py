"""Compounding: bone-mask pixels of a tracked sweep → world points in mm.

Each mask pixel ``(c, r)`` of frame ``i`` becomes ``pixel_to_world[i] · [c, r, 0, 1]ᵀ`` (see
:mod:`ultraboneudf.sweep.model`). Each point keeps where it came from: the frame index, the probe
position (the transducer element of its scan line, image-plane depth 0, in world mm) and the beam
direction (world unit vector down the scan line, away from the probe). Beams of a linear probe are
parallel, so the beam direction is the image's row axis; the surface normal seen by the probe
points roughly along ``−beam`` (use it to orient normals and to weight points by incidence).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .model import Sweep
from .transforms import pixels_to_world


@dataclass
class CompoundedPoints:
    """Points compounded from a sweep, with per-point provenance (``N`` points).

    Attributes:
        points: ``(N, 3)`` float64 world coordinates, mm.
        frame_index: ``(N,)`` int64 index of the source frame in the sweep.
        probe_position: ``(N, 3)`` float64 world position of the point's scan-line origin on the
            transducer face, mm.
        beam_direction: ``(N, 3)`` float64 unit vector along the beam (away from the probe).
        pixel: ``(N, 2)`` float64 source pixel ``(column, row)``.
    """

    points: np.ndarray
    frame_index: np.ndarray
    probe_position: np.ndarray
    beam_direction: np.ndarray
    pixel: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> "CompoundedPoints":
        """The points selected by a boolean mask or index array."""
        return CompoundedPoints(self.points[keep], self.frame_index[keep],
                                self.probe_position[keep], self.beam_direction[keep],
                                self.pixel[keep])

    @property
    def depth_mm(self) -> np.ndarray:
        """``(N,)`` distance from the probe face along the beam, mm."""
        return np.einsum("ij,ij->i", self.points - self.probe_position, self.beam_direction)

    def as_dict(self) -> dict[str, np.ndarray]:
        """Arrays by name (for ``np.savez``)."""
        return {"points": self.points, "frame_index": self.frame_index,
                "probe_position": self.probe_position, "beam_direction": self.beam_direction,
                "pixel": self.pixel}

    @classmethod
    def empty(cls) -> "CompoundedPoints":
        """No points."""
        z3 = np.zeros((0, 3))
        return cls(z3, np.zeros(0, np.int64), z3.copy(), z3.copy(), np.zeros((0, 2)))

    @classmethod
    def concatenate(cls, parts: list["CompoundedPoints"]) -> "CompoundedPoints":
        """Join several sets in order."""
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("points", "frame_index", "probe_position", "beam_direction", "pixel")))


def top_boundary(mask: np.ndarray) -> np.ndarray:
    """Keep, per column (scan line), only the shallowest pixel of a ``(H, W)`` mask.

    The bone surface is the top of the echo; thick masks otherwise bias the surface into the bone.
    """
    m = np.asarray(mask, dtype=bool)
    out = np.zeros_like(m)
    cols = np.flatnonzero(m.any(axis=0))
    out[np.argmax(m[:, cols], axis=0), cols] = True
    return out


def compound(sweep: Sweep, masks: np.ndarray | None = None, top_only: bool = False,
             frame_step: int = 1, advance: Any = None) -> CompoundedPoints:
    """Map the bone pixels of every frame to world mm.

    Args:
        sweep: the tracked sweep.
        masks: ``(F, H, W)`` bone masks; the sweep's own masks by default.
        top_only: keep only the top boundary of each mask column (:func:`top_boundary`).
        frame_step: use every ``frame_step``-th frame.
        advance: optional progress callback, called once per frame.

    Returns:
        :class:`CompoundedPoints` in frame order.
    """
    m = sweep.masks if masks is None else np.asarray(masks, dtype=bool)
    if m is None:
        raise ValueError("the sweep has no masks; segment it first")
    if m.shape != (sweep.n_frames, sweep.height, sweep.width):
        raise ValueError(f"masks have shape {m.shape}, expected "
                         f"({sweep.n_frames}, {sweep.height}, {sweep.width})")
    p2w = sweep.pixel_to_world()
    parts: list[CompoundedPoints] = []
    for i in range(0, sweep.n_frames, max(1, int(frame_step))):
        mask = top_boundary(m[i]) if top_only else m[i]
        rows, cols = np.nonzero(mask)
        if advance is not None:
            advance(max(1, int(frame_step)))
        if len(rows) == 0:
            continue
        pts = pixels_to_world(p2w[i], cols, rows)
        # the scan line's origin: image-plane depth 0, i.e. row = −offset
        probe = pixels_to_world(p2w[i], cols, np.full(len(cols), -sweep.pixel_offset))
        beam = p2w[i, :3, 1]  # along the scan line (a sheared calibration tilts it off ŷ)
        parts.append(CompoundedPoints(
            points=pts, frame_index=np.full(len(rows), i, dtype=np.int64), probe_position=probe,
            beam_direction=np.broadcast_to(beam / np.linalg.norm(beam), pts.shape).copy(),
            pixel=np.stack([cols, rows], axis=1).astype(np.float64)))
    return CompoundedPoints.concatenate(parts)
