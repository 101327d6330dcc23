"""Frame-to-frame registration of a compounded sweep: rigid per-frame corrections of tracking error.

A tracker's error moves each whole frame rigidly, so neighbouring slices of one bone surface are
offset from each other (by about the tracking error along the surface normal, 0.2–0.3 mm for a
good optical tracker). :func:`align_frames` measures, for every frame, how far its points lie from
the local surface of the *other* frames around them (a robust plane fitted to their points within
``radius_mm``, as in :mod:`ultraboneudf.geometry.surface_fit`, the frame's own points left out),
and moves the frame by the small rigid motion that cancels it. The motion has the two degrees of
freedom an image of a surface facing the probe can measure: a translation along the frame's beams
and a rotation about the normal of its image plane (through the frame's centroid); sliding along
the bone is invisible in the points and is left alone. Tukey weights against the frame's own
robust spread keep false echoes from pulling, and a Gaussian prior keeps a frame with little
surface near no motion.

It is one estimate, not an iteration: each frame is compared with its neighbours as recorded.
Iterating (moving frames toward neighbours that move too) converges to a configuration in which
every frame agrees with its neighbours but not with the bone: the smooth part of the tracking error
is invisible from inside the sweep and drifts. For the same reason the part of the corrections
common to all frames is removed, and only frames with other frames on both sides within the radius
are moved: an end frame's neighbours lie on one side, where a curved bone drops away.

A frame whose neighbourhood holds no other frame (a sweep with frames centimetres apart) or too
few surface points is left where the tracker put it. Lengths are in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.neighbors import kd_tree
from ..geometry.surface_fit import robust_quadric_fit
from ..geometry.vectors import unit_rows
from .compound import CompoundedPoints

_TUKEY = 3.0           # a point weighs nothing beyond this many robust spreads of its frame
_MIN_SPREAD_MM = 0.05  # floor of a frame's robust spread (a perfectly clean frame is not infinitely sure)
_SIDE = 0.25           # a neighbour is on one side when it lies this × the radius off the frame's plane


@dataclass
class AlignmentReport:
    """What :func:`align_frames` did.

    Attributes:
        frames: frames with points.
        aligned: frames moved (other frames on both sides, enough surface points).
        residual_before_mm: robust spread (1.4826 × median absolute value) of the sampled points'
            heights above the other frames' surface, before alignment.
        residual_after_mm: the same after.
        median_shift_mm: median translation of a moved frame's centroid.
        max_shift_mm: the largest translation of a frame's centroid.
        max_angle_deg: the largest rotation of a frame.
    """

    frames: int
    aligned: int
    residual_before_mm: float
    residual_after_mm: float
    median_shift_mm: float
    max_shift_mm: float
    max_angle_deg: float

    def as_dict(self) -> dict:
        """The fields for JSON (lengths rounded to 0.1 µm; an undefined spread is ``None``)."""
        return {k: ((round(v, 4) if np.isfinite(v) else None) if isinstance(v, float) else v)
                for k, v in self.__dict__.items()}

    def summary(self) -> str:
        """One line for the log."""
        if not self.aligned:
            return f"no frame of {self.frames} has neighbouring frames on both sides to align to"
        return (f"{self.aligned} of {self.frames} frames aligned to their neighbours (median "
                f"{self.median_shift_mm:.2f} mm, at most {self.max_shift_mm:.2f} mm and "
                f"{self.max_angle_deg:.2f}°); point-to-neighbours spread {self.residual_before_mm:.2f} → "
                f"{self.residual_after_mm:.2f} mm")


def align_frames(cp: CompoundedPoints, radius_mm: float = 6.0, sample_mm: float = 0.5,
                 prior_mm: float = 0.5, prior_deg: float = 0.5, min_points: int = 20,
                 max_neighbors: int = 128) -> tuple[CompoundedPoints, AlignmentReport]:
    """Rigidly register every frame of a compounded sweep to its neighbours (see module doc).

    Args:
        cp: the compounded points (mm) with their frame indices, probe positions and beams.
        radius_mm: radius of the other frames' local surface around each point.
        sample_mm: the points are thinned to one per ``sample_mm`` cube of each frame for the
            estimate (every point is moved).
        prior_mm: prior standard deviation of a frame's translation error along its beams.
        prior_deg: prior standard deviation of a frame's in-plane rotation error, degrees.
        min_points: a frame needs this many sampled points on the other frames' surface.
        max_neighbors: neighbours looked up per sampled point (of every frame).

    Returns:
        ``(aligned points, report)``: a new :class:`CompoundedPoints` (points, probe positions and
        beam directions moved with their frames; ``cp`` is not modified).
    """
    out = CompoundedPoints(cp.points.copy(), cp.frame_index.copy(), cp.probe_position.copy(),
                           cp.beam_direction.copy(), cp.pixel.copy())
    _, frame = np.unique(cp.frame_index, return_inverse=True)
    n_frames = int(frame.max()) + 1 if len(frame) else 0
    if n_frames < 2:
        return out, AlignmentReport(n_frames, 0, float("nan"), float("nan"), 0.0, 0.0, 0.0)
    sample = _thin_per_frame(cp.points, frame, sample_mm)
    beam, elevation, centroid = _frame_axes(cp, frame, n_frames)
    height, normal, ok, sides = _heights(out, sample, frame, elevation, radius_mm, max_neighbors)
    before = _robust_spread(height[ok])
    coef, enough = _solve(out.points[sample], frame[sample], height, normal, ok, beam, elevation,
                          centroid, np.array([np.radians(prior_deg), prior_mm]), min_points)
    move = enough & (np.bincount(frame[sample], weights=sides, minlength=n_frames)
                     >= 0.5 * np.bincount(frame[sample], minlength=n_frames))
    coef[~move] = 0.0
    if move.any():
        coef[move] -= coef[move].mean(axis=0)  # the sweep as a whole is not observable
    _apply(out, frame, coef, beam, elevation, centroid)
    after_h, _, after_ok, _ = _heights(out, sample, frame, elevation, radius_mm, max_neighbors)
    shift = np.abs(coef[:, 1])
    return out, AlignmentReport(n_frames, int(move.sum()), before, _robust_spread(after_h[after_ok]),
                                float(np.median(shift[move])) if move.any() else 0.0,
                                float(shift.max(initial=0.0)),
                                float(np.degrees(np.abs(coef[:, 0]).max(initial=0.0))))


def _thin_per_frame(points: np.ndarray, frame: np.ndarray, step: float) -> np.ndarray:
    """Indices of one point per ``step`` cube of each frame (the first in input order)."""
    if step <= 0:
        return np.arange(len(points))
    cells = np.floor((points - points.min(axis=0)) / step).astype(np.int64)
    _, first = np.unique(np.column_stack([frame, cells]), axis=0, return_index=True)
    return np.sort(first)


def _frame_axes(cp: CompoundedPoints, frame: np.ndarray, n_frames: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame (F, 3): the unit beam direction, the unit normal of the image plane (beam ×
    the points' lateral direction) and the centroid of its points."""
    counts = np.maximum(np.bincount(frame, minlength=n_frames), 1)[:, None]
    centroid = np.zeros((n_frames, 3))
    np.add.at(centroid, frame, cp.points)
    centroid /= counts
    beam = np.zeros((n_frames, 3))
    np.add.at(beam, frame, cp.beam_direction)
    beam = unit_rows(beam)
    # the lateral direction: the principal axis of the points across the beams
    d = cp.points - centroid[frame]
    d -= np.einsum("ni,ni->n", d, beam[frame])[:, None] * beam[frame]
    scatter = np.zeros((n_frames, 3, 3))
    np.add.at(scatter, frame, d[:, :, None] * d[:, None, :])
    lateral = np.linalg.eigh(scatter)[1][:, :, 2]
    elevation = unit_rows(np.cross(beam, lateral))
    return beam, elevation, centroid


def _heights(cp: CompoundedPoints, sample: np.ndarray, frame: np.ndarray, elevation: np.ndarray,
             radius: float, max_neighbors: int, chunk: int = 4096
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each sampled point (M): its signed height above the robust plane of the *other* frames'
    sampled points within ``radius`` (toward the probe), that plane's unit normal (M, 3, toward the
    probe), whether the plane is accepted, and whether other frames lie on both sides of the
    point's image plane."""
    pts, fr = cp.points[sample], frame[sample]
    view = unit_rows(pts - cp.probe_position[sample])
    tree = kd_tree(pts)
    k = int(min(max_neighbors, len(pts)))
    m = len(pts)
    height, normal = np.zeros(m), np.zeros((m, 3))
    ok, sides = np.zeros(m, dtype=bool), np.zeros(m, dtype=bool)
    for start in range(0, m, chunk):
        sl = slice(start, start + chunk)
        dist, idx = tree.query(pts[sl], k=k, distance_upper_bound=radius, workers=-1)
        dist, idx = dist.reshape(-1, k), np.minimum(idx.reshape(-1, k), m - 1)
        other = np.isfinite(dist) & (fr[idx] != fr[sl, None])  # the frame's own points left out
        # a plane, not the quadric: fitted to other frames only, a quadric's curvature along the
        # sweep would follow their offsets and extrapolate them to this frame amplified
        fit = robust_quadric_fit(pts[sl], pts[idx], dist, other, radius, view[sl], quadric=False)
        flip = np.where(np.einsum("ci,ci->c", fit.normal, view[sl]) > 0, -1.0, 1.0)
        height[sl], normal[sl], ok[sl] = fit.offset * flip, fit.normal * flip[:, None], fit.accepted
        elev = np.einsum("cki,ci->ck", pts[idx] - pts[sl, None], elevation[fr[sl]])
        sides[sl] = ((other & (elev > _SIDE * radius)).any(axis=1)
                     & (other & (elev < -_SIDE * radius)).any(axis=1))
    return height, normal, ok, sides


def _robust_spread(values: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(values))) if len(values) else float("nan")


def _solve(pts: np.ndarray, fr: np.ndarray, height: np.ndarray, normal: np.ndarray, ok: np.ndarray,
           beam: np.ndarray, elevation: np.ndarray, centroid: np.ndarray, prior: np.ndarray,
           min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Per frame (F, 2): the rotation (rad, about the image plane's normal through the centroid)
    and translation (mm, along the beam) that cancel its points' heights — Tukey-weighted least
    squares against the frame's robust spread with the Gaussian ``prior`` (std of each) — and
    whether the frame had ``min_points`` weighed points (F,) bool."""
    n_frames = len(beam)
    fr, pts, h, n = fr[ok], pts[ok], height[ok], normal[ok]
    spread = np.full(n_frames, np.inf)
    order = np.argsort(fr, kind="stable")
    bounds = np.searchsorted(fr[order], np.arange(n_frames + 1))
    for f in np.flatnonzero(np.diff(bounds)):
        spread[f] = max(_robust_spread(h[order[bounds[f]:bounds[f + 1]]]), _MIN_SPREAD_MM)
    s = spread[fr]
    u = h / (_TUKEY * s)
    w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0) / (s * s)
    # a point moves by θ e × (p − c) + τ b, so its height by θ ((p − c) × n)·e + τ n·b
    jac = np.stack([np.einsum("mi,mi->m", np.cross(pts - centroid[fr], n), elevation[fr]),
                    np.einsum("mi,mi->m", n, beam[fr])], axis=1)
    a = np.zeros((n_frames, 2, 2))
    b = np.zeros((n_frames, 2))
    np.add.at(a, fr, w[:, None, None] * jac[:, :, None] * jac[:, None, :])
    np.add.at(b, fr, -(w * h)[:, None] * jac)
    a += np.diag(1.0 / prior ** 2)
    coef = np.linalg.solve(a, b[..., None])[..., 0]
    used = np.bincount(fr, weights=(w > 0).astype(float), minlength=n_frames)
    return coef, used >= min_points


def _apply(cp: CompoundedPoints, frame: np.ndarray, coef: np.ndarray, beam: np.ndarray,
           elevation: np.ndarray, centroid: np.ndarray) -> None:
    """Move each frame's points, probe positions and beams in place by its rotation ``coef[:, 0]``
    about its image plane's normal through ``centroid`` and translation ``coef[:, 1]`` along its
    beam."""
    rot = Rotation.from_rotvec(coef[:, :1] * elevation).as_matrix()        # (F, 3, 3)
    r, c, t = rot[frame], centroid[frame], coef[frame, 1:] * beam[frame]
    cp.points = np.einsum("nij,nj->ni", r, cp.points - c) + c + t
    cp.probe_position = np.einsum("nij,nj->ni", r, cp.probe_position - c) + c + t
    cp.beam_direction = np.einsum("nij,nj->ni", r, cp.beam_direction)


__all__ = ["align_frames", "AlignmentReport"]
