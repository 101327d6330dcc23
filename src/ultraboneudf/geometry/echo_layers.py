"""False echoes that lie in front of the bone, and clusters detached from it.

Real ultrasound bone clouds hold, besides the bone's own band of echoes, soft tissue that the
segmentation took for bone: fascia and tendon sheets, clusters and streaks along the beam. Measured
against CT on real clouds (docs/real_data.md), almost every point more than 5 mm off the bone lies
*outside* it, between the bone and the probe, and the bone's band is the densest layer of echoes
along its normal. A local plane fit keeps such sheets, since each is a smooth surface of its own;
what gives them away is their place: in front of a denser surface. This module finds them from the
bone's side:

1. **Columns of the dense surface.** Representatives of the points whose local plane was accepted at
   the first radius and whose neighbourhood is at least half as dense as the cloud's median (one per
   ``spacing`` voxel) each look along their normal, oriented toward the probe's side, in a
   cylinder of radius ``lateral``: the points between ``gap`` and ``depth`` in front of it whose
   layer (±1 mm along the column) holds less than ``1 / ratio`` of the representative's own layer
   are counted as lying in front of the bone. A point so counted by ``votes`` columns is a false
   echo. Echoes *behind* a layer are left alone: the two faces of a thin plate of bone (the iliac
   wing) are each other's back side, and both are bone.
2. **The probe's side.** With a sweep's probe positions the front of a plane is the side of its
   probe, and an echo counted in front must also have the dense surface under it on its own beam
   (the beam that imaged a false echo went on to the bone; one that imaged bone stopped there,
   whatever bone other beams saw behind it, as in the hollows of a small bone). A compounded cloud has none; bone, seen from outside, is mostly convex, so the front of a
   representative's plane is the side away from which its neighbours within ``convexity`` bend (the
   median height of the representatives around it above its plane is negative), made consistent
   with its neighbours' choice within ``2 × spacing`` by a majority vote. A cloud that kept its
   frames' order tells its beams (:mod:`~ultraboneudf.geometry.frame_order`): there the front is
   the side the beams of the points around the representative come from, and convexity decides
   only where they tell nothing or graze its plane (the same vote follows). Beams that lie mostly
   along the surface are not beams (the order was another one) and are ignored; beams from which
   most representatives' front would be the other side than convexity's come from a cloud listed
   from the far end of its beams, and are turned.
3. **Detached clusters.** What is left is split into groups linked by gaps under ``link``; groups
   with fewer points than ``fraction`` of the largest are dropped (clusters of echoes floating in
   the soft tissue, which no column reached), unless they hold echoes of a steep face (a sweep's
   steep planes, :func:`~ultraboneudf.geometry.surface_fit.fit_local_planes`): the few echoes a
   small bone's steep sides return lie apart from the rest; or unless they continue the kept
   surface in its own plane (:func:`along_the_surface`): bone seen apart from the rest, past a gap
   in the coverage.

Lengths are in the cloud's unit (the pipeline works in mm, before normalisation).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .neighbors import KDTree, kd_tree
from .surface_fit import LocalPlanes, shadowed
from .voxel import voxel_groups

_LAYER_BIN = 1.0      # mm: the column's histogram bin; a layer is three bins (±1.5 mm)
_OWN_LAYER = 2.0      # mm: the representative's own layer is the densest within this of its plane
_CHUNK = 256          # representatives per vectorised block (≈ 10⁶ pairs)
_CONSENSUS_ROUNDS = 3
_CONVEXITY = 20.0     # mm: the scale at which bone is convex (a femoral shaft's radius is 12-15 mm)
_DENSE = 0.5          # a representative's neighbourhood holds at least this × the median count
_BEAM_TOLERANCE = 1.0  # mm: how near its beam the bone under a sweep's false echo lies
_ALONG_DEG = 35.0     # a detached group within this of the kept surface's plane continues it
_SURFACE_REACH = 2.5  # × the groups' link: the extent of the kept surface's plane a group is held to
_SLICE_MM = 0.5       # mm: a group thinner than this across its own plane lies in one image plane
_BEAM_NEIGHBOURS = 8  # a representative's front: the beams of this many points nearest to it
_BEAM_MAX_DEG = 60.0  # beams further than this from a plane's normal graze it; mostly so: not beams


def false_echoes(points: np.ndarray, planes: LocalPlanes, view: np.ndarray | None, *, depth: float,
                 ratio: float, votes: int = 2, fraction: float = 0.0, beams: np.ndarray | None = None
                 ) -> np.ndarray:
    """(N,) bool: the false echoes among ``points`` (N, 3) with their local ``planes``
    (:func:`~ultraboneudf.geometry.surface_fit.fit_local_planes`): those in front of a denser layer
    (``depth`` > 0; counted by ``votes`` columns, ``ratio``: how much denser) and, with ``fraction``
    > 0, the detached clusters left but for those holding a steep plane's points (a steep face
    returns a few echoes apart from the rest of a small bone; only sweeps have steep planes) and
    those of at least the planes' median point count that continue the kept surface in its plane.
    ``view`` (N, 3): unit directions probe → point where known. ``beams`` (N, 3): without ``view``,
    the beams a compounded cloud's order tells (zero rows where it tells none), for the columns'
    front only.
    The columns' radius and the least height in front are the planes' first radius and three
    quarters of it (the band of a bone's echoes is about that thick), representatives are spaced at
    half of it, and clusters are linked across gaps under it."""
    pts = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(pts), dtype=bool)
    radius = planes.base
    if len(pts) == 0 or radius <= 0:
        return out
    if depth > 0:
        strong = planes.valid & (planes.radius <= radius) & (planes.count >= _DENSE * np.median(planes.count))
        reps = representatives(pts, strong, radius / 2.0)
        if len(reps):
            tree = kd_tree(pts)
            if view is not None:
                front = planes.normal[reps] * np.where(
                    np.einsum("ij,ij->i", planes.normal[reps], view[reps]) > 0, -1.0, 1.0)[:, None]
            else:
                front = front_orientation(pts[reps], planes.normal[reps], _CONVEXITY, radius)
                if beams is not None:
                    front = beam_front(pts, reps, front, beams, radius, tree)
            out = in_front_of_denser_layer(pts, reps, front, depth=depth, lateral=radius,
                                           gap=0.75 * radius, ratio=ratio, tree=tree) >= votes
            if view is not None:
                # the beam that imaged a false echo in front of the bone went on to the bone; one
                # that imaged bone stopped there, whatever bone other beams saw behind it
                rows = np.flatnonzero(out)
                out[rows] = shadowed(pts[rows], -view[rows], 0.75 * radius, depth, _BEAM_TOLERANCE,
                                     occluders=pts[strong])
    if fraction > 0:
        rows = np.flatnonzero(~out)
        out[rows[small_components(pts[rows], radius, fraction, planes.steep[rows], planes.normal[rows],
                                  int(np.median(planes.count)))]] = True
    return out


def representatives(points: np.ndarray, strong: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of one ``strong`` point per occupied voxel of edge ``spacing`` (the first in index
    order, so the choice is deterministic)."""
    rows = np.flatnonzero(strong)
    if len(rows) == 0:
        return rows
    groups, _ = voxel_groups(points[rows], spacing, origin=points.min(axis=0) - spacing / 2.0)
    _, first = np.unique(groups, return_index=True)
    return rows[np.sort(first)]


def front_orientation(points: np.ndarray, normals: np.ndarray, convexity: float, consensus: float
                      ) -> np.ndarray:
    """``normals`` (R, 3) of the planes at ``points`` (R, 3), signed to point away from the bone
    (see the module docstring: convex outward, then a majority vote within ``consensus``). The bend
    is measured against the points thinned to one per ``consensus`` voxel."""
    coarse = points[representatives(points, np.ones(len(points), dtype=bool), consensus)]
    tree = kd_tree(coarse)
    height = np.zeros(len(points))
    for start in range(0, len(points), _CHUNK):
        rows = np.arange(start, min(start + _CHUNK, len(points)))
        owner, other = _pairs(tree.query_ball_point(points[rows], convexity, workers=-1))
        t = np.einsum("ij,ij->i", coarse[other] - points[rows][owner], normals[rows][owner])
        height[rows] = _group_median(t, owner, len(rows))
    return majority(points, normals * np.where(height > 0, -1.0, 1.0)[:, None], consensus)


def majority(points: np.ndarray, front: np.ndarray, consensus: float) -> np.ndarray:
    """``front`` (R, 3) at ``points`` (R, 3), each turned where it disagrees with most of those
    within ``consensus`` of it (a few rounds)."""
    owner, other = _pairs(kd_tree(points).query_ball_point(points, consensus, workers=-1))
    for _ in range(_CONSENSUS_ROUNDS):
        agree = np.bincount(owner, weights=np.einsum("ij,ij->i", front[owner], front[other]),
                            minlength=len(points))
        front = front * np.where(agree < 0, -1.0, 1.0)[:, None]
    return front


def beam_front(points: np.ndarray, reps: np.ndarray, convex: np.ndarray, beams: np.ndarray,
               consensus: float, tree: KDTree | None = None) -> np.ndarray:
    """(R, 3): the front of each representative ``reps`` (R,) of ``points`` (N, 3) from the
    ``beams`` (N, 3; zero where unknown) of its nearest points: its normal turned against their
    sum; ``convex`` (R, 3), the convexity rule's front, where they tell nothing or meet the plane at
    more than ``_BEAM_MAX_DEG``, and for all of them when the beams are not beams (module
    docstring); then the neighbours' vote within ``consensus``. ``tree``: a KD-tree of ``points``
    already built."""
    tree = kd_tree(points) if tree is None else tree
    _, near = tree.query(points[reps], k=min(_BEAM_NEIGHBOURS, len(points)), workers=-1)
    summed = beams[near.reshape(len(reps), -1)].sum(axis=1)
    length = np.linalg.norm(summed, axis=1)
    towards = np.einsum("ij,ij->i", convex, summed)  # > 0: the beams run along convexity's front
    incidence = np.abs(towards) / np.maximum(length, 1e-12)
    steep = np.cos(np.radians(_BEAM_MAX_DEG))
    told = length > 0
    if not told.any() or np.median(incidence[told]) < steep:
        return convex
    # a grazing beam's side turns with a few degrees' error of the beam or of the plane
    told &= incidence >= steep
    if not told.any():
        return convex
    against = towards > 0
    if np.mean(against[told]) > 0.5:  # most beams run out of the bone: listed from the far end
        against = ~against
    return majority(points[reps], np.where((told & against)[:, None], -convex, convex), consensus)


def in_front_of_denser_layer(points: np.ndarray, reps: np.ndarray, front: np.ndarray, *, depth: float,
                             lateral: float, gap: float, ratio: float, tree: KDTree | None = None
                             ) -> np.ndarray:
    """(N,) int: for every point, the number of representatives ``reps`` (R,) whose column (normal
    ``front`` (R, 3), toward the probe) holds it between ``gap`` and ``depth`` in front, in a layer
    less than ``1 / ratio`` as dense as the representative's own. ``tree``: a KD-tree of ``points``
    already built."""
    tree = kd_tree(points) if tree is None else tree
    edges = np.arange(-_OWN_LAYER - _LAYER_BIN, depth + _LAYER_BIN, _LAYER_BIN)
    nbins = len(edges) - 1
    own = (edges[:-1] + _LAYER_BIN / 2 >= -_OWN_LAYER) & (edges[:-1] + _LAYER_BIN / 2 <= _OWN_LAYER)
    # the column is gathered as balls along its axis, a column radius apart, that cover it
    steps = np.arange(edges[0], edges[-1] + lateral, lateral)
    ball = float(np.hypot(lateral, lateral / 2.0))
    votes = np.zeros(len(points), dtype=np.int64)
    for start in range(0, len(reps), _CHUNK):
        block = reps[start:start + _CHUNK]
        axis = front[start:start + _CHUNK]
        centres = points[block][:, None, :] + steps[None, :, None] * axis[:, None, :]
        owner, other = _pairs(tree.query_ball_point(centres.reshape(-1, 3), ball, workers=-1))
        owner //= len(steps)
        key = np.unique(owner * len(points) + other)  # a point in two balls of a column counts once
        owner, other = key // len(points), key % len(points)
        offset = points[other] - points[block][owner]
        t = np.einsum("ij,ij->i", offset, axis[owner])
        across = np.einsum("ij,ij->i", offset, offset) - t * t
        keep = (across < lateral * lateral) & (t >= edges[0]) & (t < edges[-1])
        owner, other, t = owner[keep], other[keep], t[keep]
        bins = np.minimum(((t - edges[0]) / _LAYER_BIN).astype(np.int64), nbins - 1)
        hist = np.bincount(owner * nbins + bins, minlength=len(block) * nbins).reshape(len(block), nbins)
        layer = hist.astype(np.float64)
        layer[:, 1:] += hist[:, :-1]
        layer[:, :-1] += hist[:, 1:]
        # the representative's own layer: the densest within ±2 mm of it (it may sit at the band's edge)
        peak = np.flatnonzero(own)[0] + np.argmax(layer[:, own], axis=1)
        mine = layer[np.arange(len(block)), peak]
        thin = layer[owner, bins] * ratio < mine[owner]
        above = t - (edges[peak] + _LAYER_BIN / 2)[owner]
        votes += np.bincount(other[(above > gap) & thin], minlength=len(points))
    return votes


def small_components(points: np.ndarray, link: float, fraction: float, spare: np.ndarray | None = None,
                     normals: np.ndarray | None = None, min_points: int = 3) -> np.ndarray:
    """(N,) bool: points of the groups (linked by gaps under ``link``) with fewer points than
    ``fraction`` of the largest group, but for the groups holding a point ``spare`` (N,) bool marks
    and, given the points' plane ``normals`` (N, 3), those of ``min_points`` or more that continue
    the kept surface in its own plane (:func:`along_the_surface`)."""
    if len(points) == 0 or fraction <= 0:
        return np.zeros(len(points), dtype=bool)
    pairs = kd_tree(points).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    _, label = connected_components(graph, directed=False)
    size = np.bincount(label)
    small = size < fraction * size.max()
    if spare is not None:
        small &= np.bincount(label, weights=spare.astype(np.float64), minlength=len(size)) == 0
    if normals is not None and small.any() and not small.all():
        small &= ~along_the_surface(points, label, small, normals, _SURFACE_REACH * link, min_points)
    return small[label]


def along_the_surface(points: np.ndarray, label: np.ndarray, candidate: np.ndarray, normals: np.ndarray,
                      reach: float, min_points: int = 3) -> np.ndarray:
    """(G,) bool over the groups ``label`` (N,) numbers: the ``candidate`` groups of ``min_points``
    or more that lie in the plane of the surface the other groups form, where it is nearest to them.

    A piece of bone seen apart from the rest (another pass of the sweep, past a gap in the coverage)
    continues the bone's surface, while a cluster of echoes floating in the soft tissue lies off it,
    along its normal. A group is judged at the nearest point of the rest: both the median elevation
    of its points over that point's own plane (``normals`` (N, 3)) and the elevation of its centroid
    over the plane of the rest within ``reach`` of that point must stay under ``_ALONG_DEG``. A
    group that lies in one plane (thinner than ``_SLICE_MM`` across it) is one frame's curve, which
    no other frame confirms: it is not judged (a sweep's slices of a neighbouring bone or of soft
    tissue lie so), nor is a group of fewer points than a local plane holds (``min_points``: a few
    echoes' elevation says little)."""
    out = np.zeros(len(candidate), dtype=bool)
    rest = np.flatnonzero(~candidate[label])
    tree = kd_tree(points[rest])
    limit = np.sin(np.radians(_ALONG_DEG))
    for g in np.flatnonzero(candidate & (np.bincount(label, minlength=len(candidate)) >= max(min_points, 3))):
        own = points[label == g]
        if np.sqrt(max(np.linalg.eigvalsh(np.cov(own.T))[0], 0.0)) < _SLICE_MM:
            continue  # one image plane's curve: one frame's detection, not a piece of surface
        dist, near = tree.query(own, workers=-1)
        anchor = rest[near]
        offset = own - points[anchor]
        length = np.maximum(np.linalg.norm(offset, axis=1), 1e-12)
        rise = np.abs(np.einsum("ij,ij->i", offset, normals[anchor])) / length
        if np.median(rise) >= limit:
            continue
        base = points[rest[near[np.argmin(dist)]]]
        local = points[rest[tree.query_ball_point(base, reach)]]
        centre = local.mean(axis=0)
        _, vectors = np.linalg.eigh((local - centre).T @ (local - centre))
        towards = own.mean(axis=0) - centre
        out[g] = abs(towards @ vectors[:, 0]) < limit * max(float(np.linalg.norm(towards)), 1e-12)
    return out


def _pairs(neighbours) -> tuple[np.ndarray, np.ndarray]:
    """A ball query's lists flattened to (owner, neighbour) index pairs."""
    counts = np.fromiter((len(n) for n in neighbours), dtype=np.int64, count=len(neighbours))
    owner = np.repeat(np.arange(len(neighbours)), counts)
    other = np.concatenate([np.asarray(n, dtype=np.int64) for n in neighbours]) if counts.sum() else \
        np.zeros(0, dtype=np.int64)
    return owner, other


def _group_median(values: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Median of ``values`` per ``group`` id (0..n-1; pairs sorted by group), 0 for empty groups."""
    out = np.zeros(n)
    if len(values) == 0:
        return out
    order = np.lexsort((values, group))
    values, group = values[order], group[order]
    counts = np.bincount(group, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    lo = starts[has] + (counts[has] - 1) // 2
    hi = starts[has] + counts[has] // 2
    out[has] = 0.5 * (values[lo] + values[hi])
    return out
