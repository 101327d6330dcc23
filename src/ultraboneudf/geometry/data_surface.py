"""Distance to the surface a point cloud samples: across its gaps, not past its rims.

The distance to the nearest point is a poor stand-in for the distance to a sampled surface where
the samples are sparse: between the slices of a sweep, and over a run of missing frames, the
nearest point lies *beside* a query on the surface, not under it. :class:`DataSurface` answers with
the distance to the surface interpolated between the points instead — but only *between* them: a
query counts as lying over a gap when, among its ``k`` nearest points, one lies on the opposite
side of it from the nearest (in the nearest point's plane) within the local gap length ``bridge``
(also the point nearest to the query moved away from the nearest by half that length, which finds
the next slice when the ``k`` nearest all lie on the nearest's own).
There the distance is the distance to the surface through the two: where their planes agree
(normals within 10°), the planes, interpolated by in-plane distance, which average the jitter
between slices; where they do not (from 20°; a blend in between), the chord from the nearest point
to the opposite one, swept along the surface (its normal: the mean of the two normals, made
perpendicular to the chord). Planes disagree across a gap on a curved bone, and where a fit went
wrong: a plane fitted at the rim of a run of missing frames sees neighbours on one side only, and
the two rims' planes extrapolated to the middle of the gap miss the bone there by about twice the
chord's sagitta. Elsewhere — beyond the rim of an open surface, or with no plane — it is the
distance to a disc of radius ``reach`` around the nearest point in its plane (0: the point itself).
So gaps up to ``bridge`` close, and rims stay within ``reach`` of where the data end.

A sweep's gaps *between* frames — the frame spacing, and runs of frames lost when the probe lifted
or tracking dropped — are places the probe did not look, not places it found no bone
(:mod:`~ultraboneudf.geometry.frames`). Given each point's ``frame_axis`` (the normal of its image
plane) and ``frame_order`` (its frame's place in the sweep), a gap whose chord — from the nearest
point to the opposite one — joins two consecutive frames and runs across their image planes
(within 45° of that normal) closes when that chord is at most ``frame_bridge`` long. Gaps inside a
frame keep ``bridge``, and so do gaps that frames in between looked into and found no bone in.
Past the sweep's first and last image planes (``frame_end``: the direction out of the sweep there)
the probe never looked: the rim reach stops at those planes.

:meth:`DataSurface.distances` also gives the part of that distance along the surface's normal: over
a gap the same distance, elsewhere the height above the nearest point's plane (0 where it has no
plane). A sheet that runs parallel to the data a millimetre under them is far along the normal; a
surface continued in its own plane past a rim is not. And, where the nearest point's frame is known,
how far past the rim the query lies *within that frame's image plane*: there the probe looked on
past the last echo and found no bone (a small bone's silhouette, where it curves away from the
beam), whereas across the image planes it did not look.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .neighbors import kd_tree
from .vectors import unit_rows

if TYPE_CHECKING:
    from .surface_fit import LocalPlanes

_PLANES_AGREE_DEG = 10.0  # two planes within this angle interpolate a gap; from twice it, the chord
_ACROSS_FRAMES_COS = float(np.cos(np.radians(45.0)))  # a chord this close to the frame axis spans frames


class DataSurface:
    """The surface through ``points`` (N, 3) with unit ``normals`` (N, 3; zero rows: no plane, sign
    arbitrary), bridging gaps up to ``bridge`` (N,) long (0: none) and reaching ``reach`` (N,) or a
    scalar past the rims; lengths in the points' unit. ``frame_axis`` (N, 3; zero rows: unknown),
    ``frame_order`` (N,) and ``frame_bridge``: gaps between consecutive frames of a sweep close up to
    that length; ``frame_end`` (N, 3; zero rows: not in an end frame): no reach out of the sweep
    (module docstring)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, bridge: np.ndarray,
                 reach: np.ndarray | float = 0.0, k: int = 8, frame_axis: np.ndarray | None = None,
                 frame_order: np.ndarray | None = None, frame_bridge: float = 0.0,
                 frame_end: np.ndarray | None = None) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.normals = np.asarray(normals, dtype=np.float64)
        planar = np.any(self.normals != 0.0, axis=1)
        self.bridge = np.where(planar, np.asarray(bridge, dtype=np.float64), 0.0)
        self.reach = np.where(planar, np.broadcast_to(np.asarray(reach, dtype=np.float64), planar.shape), 0.0)
        self.frame_axis = None
        if frame_axis is not None and frame_order is not None and frame_bridge > 0:
            self.frame_axis = np.where(planar[:, None], np.asarray(frame_axis, dtype=np.float64), 0.0)
            self.frame_order = np.asarray(frame_order, dtype=np.float64)
            # a frame gap never closes shorter than an ordinary one
            self.frame_bridge = np.where(np.any(self.frame_axis != 0.0, axis=1),
                                         np.maximum(self.bridge, frame_bridge), self.bridge)
        self.frame_end = None if frame_end is None else np.asarray(frame_end, dtype=np.float64)
        self.k = int(min(k, len(self.points)))
        self.tree = kd_tree(self.points)

    @classmethod
    def from_planes(cls, points: np.ndarray, planes: "LocalPlanes", bridge: float, reach: float = 0.0,
                    frame_bridge: float = 0.0) -> "DataSurface":
        """The surface through ``points`` (N, 3) with their local ``planes``: gaps bridged up to
        ``bridge`` × each point's gap scale (``planes.gap``), rims reached ``reach`` × it, and, where
        the planes know the sweep's frames (``planes.frame_axis``, ``planes.frame_order``), gaps
        between consecutive frames bridged up to ``frame_bridge`` × the planes' first radius and no
        reach past the sweep's end planes (``planes.frame_end``)."""
        return cls(points, planes.normal, bridge * planes.gap, reach * planes.gap, frame_axis=planes.frame_axis,
                   frame_order=planes.frame_order, frame_bridge=frame_bridge * planes.base,
                   frame_end=planes.frame_end)

    def distance(self, x: np.ndarray, chunk: int = 65_536) -> np.ndarray:
        """(M,) distance from each row of ``x`` (M, 3) to the surface (see the module docstring)."""
        return self.distances(x, chunk)[0]

    def distances(self, x: np.ndarray, chunk: int = 65_536) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The distance (M,) from each row of ``x`` (M, 3) to the surface, its part (M,) along the
        surface's normal, and how far (M,) past the surface's rim it lies within the nearest point's
        image plane (0 over the data and its bridged gaps, and where the frames are unknown; see the
        module docstring)."""
        x = np.asarray(x, dtype=np.float64)
        out = np.empty((3, len(x)))
        for start in range(0, len(x), chunk):
            out[:, start:start + chunk] = self._distances(x[start:start + chunk])
        return out[0], out[1], out[2]

    def _distances(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        dist, idx = self.tree.query(x, k=self.k, workers=-1)
        dist, idx = dist.reshape(len(x), self.k), idx.reshape(len(x), self.k)
        first = idx[:, 0]
        n = self.normals[first]                                          # (M, 3)
        # The k nearest can all lie on the nearest point's own slice: also take the point nearest
        # to x moved away from it by half the gap length, which finds the next slice across a gap.
        toward = self.points[first] - x
        toward -= np.einsum("mi,mi->m", toward, n)[:, None] * n
        toward = unit_rows(toward)
        lengths = [self.bridge] if self.frame_axis is None else [self.bridge, self.frame_bridge]
        far = [self.tree.query(x - 0.5 * length[first, None] * toward, k=1, workers=-1)[1] for length in lengths]
        idx = np.concatenate([idx] + [np.asarray(f).reshape(-1, 1) for f in far], axis=1)
        offset = self.points[idx] - x[:, None]                           # (M, k + 1 or 2, 3)
        dist = np.linalg.norm(offset, axis=2)
        across = np.einsum("mki,mi->mk", offset, n)
        inplane = offset - across[..., None] * n[:, None]
        # neighbours on the other side of x from the nearest, within the nearest's gap length
        within = dist <= self.bridge[first, None]
        if self.frame_axis is not None:  # or in the next frame, a gap up to the frame bridge long
            step = offset - offset[:, :1]                                # from the nearest point
            length = np.linalg.norm(step, axis=2)
            spans = np.abs(np.einsum("mki,mi->mk", step, self.frame_axis[first])) >= _ACROSS_FRAMES_COS * length
            spans &= np.abs(self.frame_order[idx] - self.frame_order[first, None]) == 1
            within |= spans & (length <= self.frame_bridge[first, None])
        opposite = (np.einsum("mki,mi->mk", inplane, inplane[:, 0]) < 0) & within
        opposite[:, 0] = False
        has = opposite.any(axis=1)
        j = np.argmax(opposite, axis=1)                                  # the closest opposite one
        rows = np.arange(len(x))
        n_j = self.normals[idx[rows, j]]
        n_j = np.where((np.einsum("mi,mi->m", n_j, n) < 0)[:, None], -n_j, n_j)
        # the chord from the nearest to the opposite point, swept along the surface
        off_j = offset[rows, j]
        chord = unit_rows(off_j - offset[:, 0])
        n_c = n + n_j
        n_c = unit_rows(n_c - np.einsum("mi,mi->m", n_c, chord)[:, None] * chord)
        chord_side = -np.einsum("mi,mi->m", offset[:, 0], n_c)
        a0 = -across[:, 0]                                               # signed plane distances of x
        aj = -np.einsum("mi,mi->m", off_j, n_j)
        b0 = np.linalg.norm(inplane[:, 0], axis=1)
        bj = np.linalg.norm(inplane[rows, j], axis=1)
        planes_side = (bj * a0 + b0 * aj) / np.maximum(b0 + bj, 1e-300)
        # the planes where they agree, the chord where they do not (module docstring)
        tilt = np.degrees(np.arccos(np.clip(np.einsum("mi,mi->m", n, n_j), -1.0, 1.0)))
        w = np.clip((tilt - _PLANES_AGREE_DEG) / _PLANES_AGREE_DEG, 0.0, 1.0)
        between = np.abs((1.0 - w) * planes_side + w * chord_side)
        # past the rim: to the disc of radius reach in the nearest point's plane, cut off at the
        # sweep's end plane (the part of x's in-plane offset out of the sweep is not reached)
        beyond = np.sqrt(a0 ** 2 + np.maximum(b0 - self.reach[first], 0.0) ** 2)
        if self.frame_end is not None:
            out = self.frame_end[first]
            out = unit_rows(out - np.einsum("mi,mi->m", out, n)[:, None] * n)
            past = np.maximum(-np.einsum("mi,mi->m", inplane[:, 0], out), 0.0)
            side = np.sqrt(np.maximum(b0 ** 2 - past ** 2, 0.0))
            cut = np.sqrt(a0 ** 2 + past ** 2 + np.maximum(side - self.reach[first], 0.0) ** 2)
            beyond = np.where(past > 0.0, cut, beyond)
        seen = np.zeros(len(x))
        if self.frame_axis is not None:
            # the in-plane offset past the rim, less its part across the image planes
            axis = self.frame_axis[first]
            axis = axis - np.einsum("mi,mi->m", axis, n)[:, None] * n
            known = np.linalg.norm(axis, axis=1) > 0.5
            across_frames = np.abs(np.einsum("mi,mi->m", inplane[:, 0], unit_rows(axis)))
            within = np.sqrt(np.maximum(b0 ** 2 - across_frames ** 2, 0.0))
            seen = np.where(known & ~has, np.maximum(within - self.reach[first], 0.0), 0.0)
        return np.where(has, between, beyond), np.where(has, between, np.abs(a0)), seen
