"""Robust local planes of a point cloud: normals, noise-free positions, outliers, gap scale.

Ultrasound bone points are a thick, slice-structured band: segmentation noise along the beam
(often near a millimetre), per-frame offsets from tracking, and false echoes in the acoustic shadow
below the bone. Around every point a plane is fitted to its neighbours within a radius, with
Gaussian distance weights (σ = radius / 2) and two rounds of robust re-weighting (neighbours far
from the current plane, relative to its spread, lose their weight), so that false echoes and a
few wrong slices do not tilt it.

A neighbourhood inside one slice is a noisy line, and its best plane is the image plane, not the
surface. A fit is therefore accepted only when the neighbours spread in both directions of the
plane (``λ_mid ≥ 0.2·λ_max``) and, where the viewing direction of each point is known (a sweep:
probe → point), when the plane faces the probe within 60°: bone that steep returns little
echo, while a streak of false echoes beneath the bone, seen along the beam, makes exactly such
steep planes, and a field that followed them would raise walls across the surface. Points whose
fit is refused at the first radius are fitted again at twice and four times it: sparse slices
need a wider neighbourhood to see their neighbours.

With ``steep_deg`` (> 60°), a point that no radius gives a plane within 60° of its view, but
some radius gives one within ``steep_deg``, keeps that *steep* plane's orientation and radius, so
that the surface through the data continues past it in that plane (an echo fading on a steep face:
the bone goes on past the last detection), without being moved onto it or judged by it
(``offset`` 0, not ``valid``). A steep face returns few echoes, often too few for a plane at the
first radius: :func:`steep_echoes` finds those that a wider radius gives a steep plane, unless the
bone lies above them on their beam (false echoes in its shadow can line up into such planes too),
and :meth:`LocalPlanes.outliers` spares them.

From the fit:

* ``normal``: the plane's unit normal (sign arbitrary), ``0`` where no radius gave a plane;
* ``offset``: the point's signed height, along the normal, above the quadric fitted to the same
  neighbours in the plane's frame (a plane would flatten a curved bone by about (radius/2)²/(2R));
  ``point − offset·normal`` is the point moved onto the surface (denoised);
* ``spread``: the local noise, 1.4826 × the median distance of the 32 nearest points (on the
  surface) from their planes (a standard deviation for Gaussian noise, not inflated by a few
  outliers);
* ``radius``: the radius of the accepted fit (the scale at which the data form a surface there:
  about the gap between neighbouring slices where they are sparse), 0 where none;
* ``steep``: the fit is a steep plane (above), not one facing the view;
* ``frame_axis``, ``frame_order``, ``frame_end``: for a sweep whose frames are known, the normal
  of the image plane that imaged each point (:func:`~ultraboneudf.geometry.frames.frame_axes`),
  that frame's place among the sweep's frames (0, 1, …) and, in the first and last frame, the
  direction out of the sweep (:func:`~ultraboneudf.geometry.frames.sweep_ends`); the pipeline adds
  them, the fit does not need them; else ``None``.

Neighbours come from a copy of the cloud voxelised at ``radius / 4``, so that ``max_neighbors``
points cover the whole radius whatever the input density (a dense slice would otherwise fill the
neighbourhood with points of one line). Lengths are in the cloud's unit (the pipeline calls it in
mm, before normalisation).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from .neighbors import kd_tree
from .voxel import voxel_downsample

_ROBUST_ROUNDS = 2
_ROBUST_SCALE = 2.0      # a neighbour's weight is exp(−½ (r / (2·spread))²)
_SPAN = 0.2              # accept a plane only if λ_mid ≥ this × λ_max (not a line)
_MAX_INCIDENCE_COS = float(np.cos(np.radians(60.0)))
_MIN_NEIGHBORS = 6
_SPARSE = 0.1            # fewer neighbours than this × the median: isolated (a rim has about ½)
_WIDER = (1.0, 2.0, 4.0)  # radii tried, in units of the first
_NOISE_NEIGHBORS = 32    # points over which the local noise (spread) is taken


@dataclass
class LocalPlanes:
    """Per-point robust plane fits of ``N`` points (see the module docstring)."""

    normal: np.ndarray    # (N, 3) unit normals, zero where there is no plane
    offset: np.ndarray    # (N,) signed height of each point above its local quadric (along normal)
    spread: np.ndarray    # (N,) robust spread (scaled MAD) of the neighbours about the plane
    count: np.ndarray     # (N,) neighbours within the first radius (in its radius / 4 voxel copy)
    radius: np.ndarray    # (N,) radius of the accepted fit, 0 where none
    steep: np.ndarray     # (N,) bool: the fit is a steep plane (orientation only)
    base: float = 0.0     # the first radius tried
    frame_axis: np.ndarray | None = None   # (N, 3) sweeps: the image plane's normal (geometry.frames)
    frame_order: np.ndarray | None = None  # (N,) sweeps: the frame's place among the sweep's frames
    frame_end: np.ndarray | None = None    # (N, 3) sweeps: out of the sweep, in its first/last frame

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: a plane facing the view was fitted (the point's offset, spread and
        denoising come from it)."""
        return (self.radius > 0) & ~self.steep

    @property
    def gap(self) -> np.ndarray:
        """(N,) the gap scale of each point: its fit radius, at most twice the first radius (the
        four-fold fits give sparse slices a normal, but a surface across gaps that long would be
        invented), 0 where there is no plane (steep planes count)."""
        return np.minimum(self.radius, 2.0 * self.base)

    def projected(self, points: np.ndarray) -> np.ndarray:
        """``points`` (N, 3) moved onto their planes (unchanged where there is none)."""
        return points - self.offset[:, None] * self.normal

    @property
    def sparse(self) -> np.ndarray:
        """(N,) bool: isolated points: fewer neighbours within the first radius than a surface needs,
        or than a tenth of the cloud's median count (false echoes deeper than the radius find only
        each other, a sparse scatter)."""
        return self.count < max(_MIN_NEIGHBORS, _SPARSE * float(np.median(self.count)) if len(self.count) else 0.0)

    def outliers(self, sigmas: float, floor: float = 0.0, spare: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: points farther from their plane than ``sigmas`` × its spread (and than
        ``floor``), or :attr:`sparse`, except those ``spare`` (N,) bool marks (e.g.
        :func:`steep_echoes`)."""
        far = self.valid & (np.abs(self.offset) > np.maximum(sigmas * self.spread, floor))
        return far | (self.sparse if spare is None else self.sparse & ~spare)

    def subset(self, keep: np.ndarray) -> "LocalPlanes":
        """The fits of the points selected by a boolean mask or index array (every per-point array,
        the optional sweep ones included)."""
        return replace(self, **{f.name: getattr(self, f.name)[keep] for f in fields(self)
                                if isinstance(getattr(self, f.name), np.ndarray)})

    def scaled(self, factor: float) -> "LocalPlanes":
        """The same planes with every length multiplied by ``factor`` (a change of unit)."""
        return replace(self, offset=self.offset * factor, spread=self.spread * factor,
                       radius=self.radius * factor, base=self.base * factor)


def fit_local_planes(points: np.ndarray, radius: float, view: np.ndarray | None = None,
                     max_neighbors: int = 64, steep_deg: float = 0.0) -> LocalPlanes:
    """Robust local planes of ``points`` (N, 3), first at ``radius`` (same unit), then at twice
    and four times it where refused; ``view`` (N, 3): optional unit viewing directions (probe →
    point); ``steep_deg``: with ``view``, also the steep planes up to this angle from it (0: none).
    See the module docstring."""
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    out = LocalPlanes(np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros(n),
                      np.zeros(n, dtype=bool), float(radius))
    if n == 0 or radius <= 0:
        return out
    steep_cos = float(np.cos(np.radians(steep_deg))) if view is not None and steep_deg > 60.0 else None
    steep_normal, steep_radius = np.zeros((n, 3)), np.zeros(n)
    todo = np.arange(n)
    for level, factor in enumerate(_WIDER):
        r = radius * factor
        fit = _fit_at(pts, todo, r, None if view is None else view[todo], max_neighbors, steep_cos)
        if level == 0:
            out.count[:] = fit.count
        ok = fit.accepted
        done = todo[ok]
        out.normal[done], out.offset[done] = fit.normal[ok], fit.offset[ok]
        out.radius[done] = r
        first = fit.steep & (steep_radius[todo] == 0)  # the first radius with a steep plane
        steep_normal[todo[first]], steep_radius[todo[first]] = fit.normal[first], r
        todo = todo[~ok]
        if len(todo) == 0:
            break
    rows = todo[steep_radius[todo] > 0]  # no plane facing the view at any radius, a steep one
    out.normal[rows], out.radius[rows], out.steep[rows] = steep_normal[rows], steep_radius[rows], True
    out.spread[:] = _local_noise(out.projected(pts), out.offset, out.valid, _NOISE_NEIGHBORS)
    return out


def radius_for_density(points: np.ndarray, radius: float, target: int, most: float = 2.0,
                       sample: int = 5_000) -> float:
    """The local planes' first radius for ``points`` (N, 3): ``radius`` where the median point has
    at least ``target`` points (itself included) within it, else wider by the square root of the
    shortfall (a surface's count grows with the square of the radius), at most ``most`` ×
    ``radius``. The median is taken over an evenly strided ``sample`` of the points, so the answer
    is deterministic. ``target`` ≤ 0 or fewer than two points: ``radius`` as given."""
    pts = np.asarray(points, dtype=np.float64)
    if target <= 0 or radius <= 0 or len(pts) < 2:
        return float(radius)
    probe = pts[::max(1, len(pts) // sample)]
    count = kd_tree(pts).query_ball_point(probe, radius, return_length=True, workers=-1)
    median = float(np.median(count))
    if median >= target:
        return float(radius)
    return float(radius * min(most, np.sqrt(target / max(median, 1.0))))


def _local_noise(on_plane: np.ndarray, offset: np.ndarray, valid: np.ndarray, k: int) -> np.ndarray:
    """(N,) 1.4826 × the median |offset| of the ``k`` fitted points nearest on the surface (by
    their projections ``on_plane``, so that a point far from its plane does not pick neighbours
    as far as itself): a robust standard deviation of the points about their planes, 0 where a
    point has no plane. Taken over the points themselves, not the fit's voxel copy, whose means
    average part of the noise away."""
    out = np.zeros(len(on_plane))
    rows = np.flatnonzero(valid)
    if len(rows) == 0:
        return out
    _, idx = kd_tree(on_plane[rows]).query(on_plane[rows], k=int(min(k, len(rows))), workers=-1)
    idx = idx.reshape(len(rows), -1)
    out[rows] = 1.4826 * np.median(np.abs(offset[rows][idx]), axis=1)
    return out


def _fit_at(pts: np.ndarray, rows: np.ndarray, radius: float, view: np.ndarray | None,
            max_neighbors: int, steep_cos: float | None = None, chunk: int = 4096) -> "QuadricFit":
    """Fits of the points ``pts[rows]`` at one radius (:class:`QuadricFit`)."""
    cloud = voxel_downsample(pts, radius / 4.0)
    tree = kd_tree(cloud)
    k = int(min(max_neighbors, len(cloud)))
    m = len(rows)
    out = QuadricFit(np.zeros((m, 3)), np.zeros(m), np.zeros(m, dtype=np.int64), np.zeros(m, dtype=bool),
                     np.zeros(m, dtype=bool))
    for start in range(0, m, chunk):
        sl = slice(start, start + chunk)
        p = pts[rows[sl]]
        dist, idx = tree.query(p, k=k, distance_upper_bound=radius, workers=-1)
        dist, idx = dist.reshape(len(p), k), idx.reshape(len(p), k)
        inside = np.isfinite(dist)
        nb = cloud[np.minimum(idx, len(cloud) - 1)]                        # (C, k, 3)
        fit = robust_quadric_fit(p, nb, dist, inside, radius, None if view is None else view[sl],
                                 steep_cos=steep_cos)
        for whole, part in zip(out, fit):
            whole[sl] = part
    return out


class QuadricFit(NamedTuple):
    """:func:`robust_quadric_fit` of ``C`` points with ``k`` neighbours each."""

    normal: np.ndarray    # (C, 3) the plane's unit normal (sign arbitrary)
    offset: np.ndarray    # (C,) signed height of each point above its neighbours' quadric
    count: np.ndarray     # (C,) neighbours used
    accepted: np.ndarray  # (C,) bool: enough neighbours, spread in both directions, facing the view
    steep: np.ndarray     # (C,) bool: such a plane, but facing the view only within ``steep_cos``


def robust_quadric_fit(p: np.ndarray, nb: np.ndarray, dist: np.ndarray, inside: np.ndarray,
                       radius: float, view: np.ndarray | None = None, quadric: bool = True,
                       steep_cos: float | None = None) -> QuadricFit:
    """The robust local fit of the module docstring for ``C`` points ``p`` (C, 3) from their
    neighbours ``nb`` (C, k, 3) at distances ``dist`` (C, k), of which ``inside`` (C, k) count.

    ``quadric=False`` measures the offset from the plane instead of the quadric; ``steep_cos``
    (with ``view``): the cosine of the steepest plane that counts as ``steep``."""
    base = np.where(inside, np.exp(-0.5 * (dist / (radius / 2.0)) ** 2), 0.0)
    weight = base
    for round_ in range(_ROBUST_ROUNDS + 1):
        wsum = np.maximum(weight.sum(axis=1), 1e-300)
        centre = np.einsum("ck,cki->ci", weight, nb) / wsum[:, None]
        d = nb - centre[:, None]
        cov = np.einsum("ck,cki,ckj->cij", weight, d, d) / wsum[:, None, None]
        vals, vecs = np.linalg.eigh(cov)                               # ascending
        nrm = vecs[:, :, 0]
        r = np.einsum("cki,ci->ck", d, nrm)
        # robust scale for the re-weighting: the median distance from the plane (an echo among
        # the neighbours does not inflate it as an RMS would)
        dev = np.where(inside, np.abs(r), np.nan)
        dev[~inside.any(axis=1)] = 0.0  # no neighbour: scale 0 (as NaN → 0, without a warning)
        sd = np.nan_to_num(1.4826 * np.nanmedian(dev, axis=1))
        if round_ < _ROBUST_ROUNDS:
            scale = np.maximum(_ROBUST_SCALE * sd, 1e-12 * radius)[:, None]
            weight = base * np.exp(-0.5 * (r / scale) ** 2)
    count = inside.sum(axis=1)
    good = (count >= _MIN_NEIGHBORS) & (vals[:, 1] >= _SPAN * np.maximum(vals[:, 2], 1e-300))
    steep = np.zeros(len(p), dtype=bool)
    if view is not None:
        facing = np.abs(np.einsum("ci,ci->c", nrm, view))
        if steep_cos is not None:
            steep = good & (facing < _MAX_INCIDENCE_COS) & (facing >= steep_cos)
        good &= facing >= _MAX_INCIDENCE_COS
    own = p - centre
    offset = np.einsum("ci,ci->c", own, nrm)
    if quadric:
        offset = offset - _quadric_height(d, weight, vecs, own)
    return QuadricFit(nrm, offset, count, good, steep)


def _quadric_height(d: np.ndarray, weight: np.ndarray, vecs: np.ndarray, own: np.ndarray) -> np.ndarray:
    """Height (C,) above the plane, at each point ``own`` (C, 3) (relative to the plane's centre),
    of the quadric ``h(s, t) = a s² + b st + c t² + d s + e t + f`` fitted by weighted least squares
    to the neighbours ``d`` (C, k, 3) (relative to the centre; weights (C, k)) in the plane's frame
    ``vecs`` (C, 3, 3) (columns: normal, then the two in-plane axes). A plane flattens a curved bone
    by about ``(radius/2)²/(2·R)``; the quadric follows the curvature, so moving a point onto it
    removes noise without that bias."""
    def design(x: np.ndarray, axis_s: np.ndarray, axis_t: np.ndarray) -> np.ndarray:
        s = np.einsum("...i,...i->...", x, axis_s)
        t = np.einsum("...i,...i->...", x, axis_t)
        return np.stack([s * s, s * t, t * t, s, t, np.ones_like(s)], axis=-1)

    a = design(d, vecs[:, None, :, 2], vecs[:, None, :, 1])             # (C, k, 6)
    h = np.einsum("cki,ci->ck", d, vecs[:, :, 0])
    ata = np.einsum("ck,cki,ckj->cij", weight, a, a)
    atb = np.einsum("ck,cki,ck->ci", weight, a, h)
    # a little ridge keeps thin or sparse neighbourhoods plane-like (and empty ones solvable)
    diag = np.einsum("cii->ci", ata)
    ridge = np.where(np.arange(6) < 3, 1e-3, 1e-9) * np.maximum(diag.max(axis=1, keepdims=True), 1e-300)
    coef = np.linalg.solve(ata + ridge[:, :, None] * np.eye(6), atb[..., None])[..., 0]
    return np.einsum("ci,ci->c", design(own, vecs[:, :, 2], vecs[:, :, 1]), coef)


def steep_echoes(points: np.ndarray, view: np.ndarray, planes: LocalPlanes, margin: float) -> np.ndarray:
    """(N,) bool: the few echoes of a steep face among ``points`` (N, 3): :attr:`~LocalPlanes.sparse`
    at the first radius of their ``planes``, given a steep plane by a wider one, and not
    :func:`shadowed` (another point ``margin`` to 10 mm above them along their beam, ``view`` (N, 3);
    ``margin`` must exceed the height by which a neighbouring scan line meets the same steep face).
    A face 60–80° from the beam returns few echoes, and those few are all the sweep says of it; a
    false echo in the bone's shadow can line up with others into a steep plane too, but the bone
    lies above it on its beam."""
    sparse = planes.sparse
    out = sparse & planes.steep & (planes.radius > planes.base)
    rows = np.flatnonzero(out)
    if len(rows):
        occluders = np.asarray(points, dtype=np.float64)[~sparse]
        out[rows[shadowed(points[rows], view[rows], margin, occluders=occluders)]] = False
    return out


def shadowed(points: np.ndarray, view: np.ndarray, margin: float, depth: float = 10.0,
             tolerance: float = 0.5, occluders: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: points with another point of the cloud (or of ``occluders`` (M, 3)) above them on
    their own beam.

    ``view`` (N, 3) are unit directions down each point's beam (probe → point). Bone returns the
    first strong echo and shadows what lies beneath it, so a detection with a cloud point between
    ``margin`` and ``depth`` closer to the probe along its beam (within ``tolerance`` of the beam) is
    a false echo in that shadow. Lengths in the cloud's unit; ``margin`` must exceed the noise along
    the beam left in the points (denoise first)."""
    pts = np.asarray(points, dtype=np.float64)
    casters = pts if occluders is None else np.asarray(occluders, dtype=np.float64)
    out = np.zeros(len(pts), dtype=bool)
    if len(pts) == 0 or len(casters) < (2 if occluders is None else 1):
        return out
    tree = kd_tree(casters)
    for d in np.arange(margin, depth + 1e-9, tolerance / 2):  # probes half a tolerance apart
        dist, _ = tree.query(pts - d * view, k=1, distance_upper_bound=tolerance, workers=-1)
        out |= np.isfinite(dist)
    return out
