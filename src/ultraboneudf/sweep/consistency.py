"""Frame-to-frame consistency of detected bone surfaces.

A bone surface is continuous: where the probe moves a fraction of a millimetre between frames,
the echo found in one frame continues in its neighbours. Speckle, a wire or a flickering
reverberation found in one frame alone does not. :func:`consistent_detections` keeps a detected
surface point when some neighbouring frame that *can* see it (near enough, the point inside its
image) also has a detection near it; it does not judge frames whose neighbours are all far away
(a sparse subset of a sweep), and keeps their points.

:func:`unconfirmed_fragments` asks the same question of compounded points, whatever segmented them,
one isolated group of points at a time: a fragment seen in one or two frames, far from every other
detection, while neighbouring frames imaged the same place and found nothing there (a fascia line
or a reverberation in one frame) is removed. It needs only each point's frame and probe position,
so it also judges points already compounded (a saved cloud, a simulated sweep).

:func:`confirmed_by_frames` asks it the other way round, of the points an outlier rule removed: a
steep face returns a few weak echoes beside the dense face above it, sparse enough for the local
outlier factor to remove, yet several frames find them in the same place, and no bone lies above
them along their beam. Those are given back; false echoes in the bone's acoustic shadow and
flickers of one or two frames are not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..geometry.neighbors import kd_tree
from ..geometry.surface_fit import shadowed
from ..geometry.voxel import group_mean, voxel_groups
from ..progress import QUIET, Progress
from .compound import CompoundedPoints
from .model import Sweep
from .transforms import pixels_to_world


@dataclass
class ConsistencyReport:
    """What :func:`consistent_detections` did: ``removed``/``judged``/``kept`` point counts and the
    number of frames that had at least one neighbour near enough to judge them."""

    removed: int
    judged: int
    kept: int
    frames_judged: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def consistent_detections(sweep: Sweep, rows: np.ndarray, neighbours: int = 2, reach_mm: float = 4.0,
                          tol_mm: float = 1.5, slope: float = 1.0) -> tuple[np.ndarray, ConsistencyReport]:
    """Drop detected surface points that do not continue into neighbouring frames.

    Args:
        sweep: the sweep (its geometry is used, in mm).
        rows: ``(F, W)`` surface row per frame and scan line (NaN where none), as
            :meth:`BoneDetector.detect` gives them.
        neighbours: frames on each side that may confirm a point.
        reach_mm: a neighbour judges a point only if the point lies within this distance of the
            neighbour's image plane (and inside its image).
        tol_mm: a point is confirmed when a detection of the neighbour lies within ``tol_mm +
            slope · d`` of it, ``d`` the point's distance to the neighbour's plane (a surface
            inclined to the image plane shifts between frames).
        slope: see ``tol_mm``.

    Returns:
        ``(rows, report)``: a copy of ``rows`` with the unconfirmed points set to NaN.
    """
    rows = np.asarray(rows, dtype=np.float64)
    n, w = rows.shape
    p2w = sweep.pixel_to_world()
    w2p = np.linalg.inv(p2w)
    cols = np.arange(w, dtype=np.float64)
    points, trees = [], []
    for i in range(n):
        ok = np.isfinite(rows[i])
        pts = pixels_to_world(p2w[i], cols[ok], rows[i][ok])
        points.append((np.flatnonzero(ok), pts))
        trees.append(kd_tree(pts) if len(pts) else None)
    normals = sweep.image_to_world[:, :3, 2]
    origins = sweep.image_to_world[:, :3, 3]
    out = rows.copy()
    removed = judged = frames_judged = 0
    for i in range(n):
        idx, pts = points[i]
        if len(pts) == 0:
            continue
        confirmed = np.zeros(len(pts), dtype=bool)
        can_judge = np.zeros(len(pts), dtype=bool)
        for j in range(max(0, i - neighbours), min(n, i + neighbours + 1)):
            if j == i:
                continue
            d = np.abs((pts - origins[j]) @ normals[j])
            pix = (w2p[j][:3, :3] @ pts.T).T + w2p[j][:3, 3]
            inside = ((d <= reach_mm) & (pix[:, 0] >= 0) & (pix[:, 0] <= sweep.width - 1)
                      & (pix[:, 1] >= 0) & (pix[:, 1] <= sweep.height - 1))
            if not inside.any():
                continue
            can_judge |= inside
            if trees[j] is None:
                continue
            dist, _ = trees[j].query(pts[inside], k=1)
            confirmed[np.flatnonzero(inside)] |= dist <= tol_mm + slope * d[inside]
        drop = can_judge & ~confirmed
        if can_judge.any():
            frames_judged += 1
        judged += int(can_judge.sum())
        removed += int(drop.sum())
        out[i, idx[drop]] = np.nan
    kept = int(np.isfinite(out).sum())
    return out, ConsistencyReport(removed, judged, kept, frames_judged)


@dataclass
class FragmentReport:
    """What :func:`unconfirmed_fragments` did: ``removed`` points in ``fragments`` groups, of
    ``groups`` isolated groups of points found."""

    removed: int
    fragments: int
    groups: int

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _linked_groups(points: np.ndarray, reach_mm: float) -> np.ndarray:
    """``(N,)`` group label of each point: points are linked when the centroids of their cells
    (cubes of edge ``reach_mm / 2``) are within ``reach_mm``. Linking cells rather than points keeps
    the cost linear in the number of points on dense sweeps, where a ball of a few mm holds
    thousands of them."""
    edge = 0.5 * reach_mm
    inverse, counts = voxel_groups(points, edge, origin=edge * np.floor(points.min(axis=0) / edge))
    centroids = group_mean(points, inverse, counts)
    pairs = kd_tree(centroids).query_pairs(reach_mm, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(counts),) * 2)
    return connected_components(graph, directed=False)[1][inverse]


def _frame_planes(cp: CompoundedPoints) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{frame: (point on its image plane, unit normal)}`` from each frame's points and their
    scan-line origins, which all lie in the frame's image plane (mm); frames whose points and
    origins lie on one line have no plane and are left out."""
    planes = {}
    order = np.argsort(cp.frame_index, kind="stable")
    frames, starts = np.unique(cp.frame_index[order], return_index=True)
    for f, rows in zip(frames, np.split(order, starts[1:])):
        rows = rows[:: max(1, len(rows) // 1000)]  # a plane needs few points; bound the cost
        x = np.vstack([cp.points[rows], cp.probe_position[rows]])
        centre = x.mean(axis=0)
        _, s, vt = np.linalg.svd(x - centre, full_matrices=False)
        if len(s) == 3 and s[1] > 1e-6 * s[0]:
            planes[int(f)] = (centre, vt[2])
    return planes


def unconfirmed_fragments(cp: CompoundedPoints, reach_mm: float = 4.0, neighbours: int = 2,
                          max_frames: int = 2) -> tuple[np.ndarray, FragmentReport]:
    """Find the isolated fragments of detections that neighbouring frames do not confirm.

    The points are split into groups linked within ``reach_mm`` (a bone surface swept with frames
    closer than that is one group; a false echo away from it is a group of its own). A group seen
    in at most ``max_frames`` frames is removed when at least as many other frames within
    ``neighbours`` of those frames (in sweep order) have their image plane within ``reach_mm`` of it
    (median over its points) — they imaged that place and found nothing there. Groups in frames
    whose neighbours are farther apart than ``reach_mm`` (a sparse subset of a sweep) are not judged.

    Args:
        cp: compounded points (mm) with their frame indices and probe positions.
        reach_mm: linking distance and the largest plane distance at which a frame judges, mm.
        neighbours: frames on each side (in frame index) that may judge a group.
        max_frames: groups seen in more frames than this are kept.

    Returns:
        ``(keep, report)``: ``(N,)`` bool, False for the points of the removed fragments.
    """
    n = len(cp)
    keep = np.ones(n, dtype=bool)
    if n == 0:
        return keep, FragmentReport(0, 0, 0)
    labels = _linked_groups(np.asarray(cp.points, dtype=np.float64), reach_mm)
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels)
    planes = _frame_planes(cp)
    fragments = 0
    for rows in np.split(order, np.cumsum(counts)[:-1]):
        seen = set(np.unique(cp.frame_index[rows]).tolist())
        if len(seen) > max_frames:
            continue
        pts = cp.points[rows]
        near = {g for f in seen for g in range(f - neighbours, f + neighbours + 1)} - seen
        judges = sum(1 for g in near if g in planes
                     and np.median(np.abs((pts - planes[g][0]) @ planes[g][1])) < reach_mm)
        if judges >= len(seen):
            keep[rows] = False
            fragments += 1
    if not keep.any():  # fragments judging each other, nothing to confirm them against: no verdict
        keep[:], fragments = True, 0
    return keep, FragmentReport(int((~keep).sum()), fragments, len(counts))


def confirmed_by_frames(cp: CompoundedPoints, removed: np.ndarray, reach_mm: float = 4.0,
                        min_frames: int = 3, margin_mm: float = 2.0, depth_mm: float = 15.0,
                        tolerance_mm: float = 0.5) -> np.ndarray:
    """Of the points an outlier rule removed, those the sweep vouches for (module docstring).

    A removed point is confirmed when no kept point lies between ``margin_mm`` and ``depth_mm``
    above it along its own beam (within ``tolerance_mm`` of the beam: it is not in the acoustic
    shadow of the bone the sweep kept) and, linked within ``reach_mm`` to the other such points, it
    belongs to a group seen in at least ``min_frames`` frames. ``margin_mm`` must exceed the noise
    along the beam (2 mm: 2.5 σ where σ = 0.8 mm); ``depth_mm`` covers echoes a centimetre under
    the bone.

    Args:
        cp: compounded points (mm) with their frames and beams.
        removed: ``(N,)`` bool, True for the points the rule removed.

    Returns:
        ``(N,)`` bool, True for the removed points to give back.
    """
    removed = np.asarray(removed, dtype=bool)
    back = np.zeros(len(cp), dtype=bool)
    if not removed.any() or removed.all():
        return back
    lit = np.flatnonzero(removed)
    lit = lit[~shadowed(cp.points[lit], cp.beam_direction[lit], margin_mm, depth_mm, tolerance_mm,
                        occluders=cp.points[~removed])]
    if len(lit) == 0:
        return back
    labels = _linked_groups(np.asarray(cp.points[lit], dtype=np.float64), reach_mm)
    seen = np.unique(np.c_[labels, cp.frame_index[lit]], axis=0)[:, 0]  # one row per (group, frame)
    back[lit[np.bincount(seen)[labels] >= min_frames]] = True
    return back


def drop_unconfirmed_fragments(cp: CompoundedPoints, progress: Progress = QUIET, source: str = ""
                               ) -> tuple[CompoundedPoints, FragmentReport]:
    """``cp`` without its unconfirmed fragments (:func:`unconfirmed_fragments`, defaults) and the
    report; says on ``progress`` how many points went, prefixed with ``source`` (e.g. a file name)."""
    keep, report = unconfirmed_fragments(cp)
    if report.removed:
        progress.log(f"{source + ': ' if source else ''}removed {report.removed} points in "
                     f"{report.fragments} fragment(s) that neighbouring frames do not confirm")
    return cp.subset(keep), report


__all__ = ["consistent_detections", "ConsistencyReport", "unconfirmed_fragments", "drop_unconfirmed_fragments",
           "FragmentReport", "confirmed_by_frames"]
