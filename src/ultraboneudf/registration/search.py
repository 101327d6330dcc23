"""Global search over poses, with no initial pose: one-point hypotheses with a normal and a turn.

A pose that maps the ultrasound target onto the CT is fixed, up to a turn about the normal, by one
target point that lies on the bone and the CT surface point it lands on, with their normals
aligned. The search enumerates exactly that: a few *anchor* points of the target (flat, well
supported, spread over the cloud, so that some lie on bone and not on a false echo) × every CT
surface point on a ``ct_spacing`` grid × both signs of the anchor's normal (a plain cloud does not
say which side the probe was on) × ``turns`` turns about the normal. Each hypothesis is scored by
reading the CT's distance field at a few target points: the soft inlier share
``mean(max(0, 1 − (d/τ)²))`` (1: every point on the surface; a point farther than τ counts 0, so
false echoes cannot pull the score). A first pass with few points ranks all hypotheses; the best
are scored again with more points; the best distinct poses go to the refinement.

Everything is batched: one matrix product places a chunk of hypotheses' points, one gather reads
the field (docs/registration.md times it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..progress import Progress
from . import rigid
from .model import BoneModel
from .target import TargetCloud

_CHUNK = 16_384  # hypotheses per matrix product (32 points: ~6 MB of float32 coordinates)


@dataclass
class Candidates:
    """Poses target → CT: rotations ``(K, 3, 3)``, translations ``(K, 3)`` (mm), scores ``(K,)``
    (soft inlier share, higher is better), best first; ``hypotheses``: how many were scored."""

    rotation: np.ndarray
    translation: np.ndarray
    score: np.ndarray
    hypotheses: int = 0

    def __len__(self) -> int:
        return len(self.score)

    def take(self, index: np.ndarray) -> "Candidates":
        return Candidates(self.rotation[index], self.translation[index], self.score[index], self.hypotheses)

    @property
    def transforms(self) -> np.ndarray:
        """``(K, 4, 4)`` target → CT."""
        return rigid.homogeneous(self.rotation, self.translation)


def soft_inliers(d: np.ndarray, tau: float) -> np.ndarray:
    """Per point ``max(0, 1 − (d/τ)²)``: 1 on the surface, 0 from ``tau`` mm on."""
    return np.maximum(0.0, 1.0 - (d / np.float32(tau)) ** 2)


def score_poses(model: BoneModel, rotation: np.ndarray, translation: np.ndarray, points: np.ndarray,
                tau: float) -> np.ndarray:
    """Soft inlier share ``(H,)`` of ``points`` ``(M, 3)`` (target frame, mm) under each pose
    ``rotation`` ``(H, 3, 3)``, ``translation`` ``(H, 3)`` (target → CT), read at the field's
    nearest node (τ in mm)."""
    h = len(rotation)
    out = np.empty(h, dtype=np.float32)
    g = (points.T / model.spacing).astype(np.float32)                       # (3, M) grid units
    shift = ((translation - model.origin) / model.spacing).astype(np.float32)
    rot = rotation.astype(np.float32)
    m = points.shape[0]
    for s in range(0, h, _CHUNK):
        e = min(h, s + _CHUNK)
        y = (rot[s:e].reshape(-1, 3) @ g).reshape(e - s, 3, m) + shift[s:e, :, None]
        d = model.lookup(np.moveaxis(y, 1, 2))
        out[s:e] = soft_inliers(d, tau).mean(axis=1)
    return out


def choose_anchors(target: TargetCloud, count: int) -> np.ndarray:
    """Indices of ``count`` anchor points: among the flatter half of the target's points with at
    least half the median support, spread by farthest point sampling from the one nearest the
    cloud's median (so that a cluster of false echoes holds one anchor at most)."""
    ok = (target.flatness <= np.median(target.flatness)) & (target.neighbours >= 0.5 * np.median(target.neighbours))
    pool = np.flatnonzero(ok)
    if len(pool) == 0:
        pool = np.arange(len(target.points))
    x = target.points[pool]
    picked = [int(np.argmin(np.linalg.norm(x - np.median(target.points, axis=0), axis=1)))]
    gap = np.linalg.norm(x - x[picked[0]], axis=1)
    while len(picked) < min(count, len(x)):
        picked.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(x - x[picked[-1]], axis=1))
    return pool[np.asarray(picked)]


def ct_anchor_points(model: BoneModel, spacing: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of the CT samples kept on a ``spacing`` mm grid (one per occupied cell, chosen at
    random with ``rng``)."""
    order = rng.permutation(len(model.points))
    cell = np.floor(model.points[order] / spacing).astype(np.int64)
    _, first = np.unique(cell, axis=0, return_index=True)
    return order[np.sort(first)]


def global_search(model: BoneModel, target: TargetCloud, rng: np.random.Generator, *, anchors: int,
                  turns: int, ct_spacing: float, tau: float, first_points: int, second_points: int,
                  keep: int, progress: Progress | None = None) -> Candidates:
    """All one-point hypotheses (see the module's text) scored in two passes; returns the ``keep``
    best of the second pass, best first (poses target → CT)."""
    x = target.points
    chosen = choose_anchors(target, anchors)
    ct = ct_anchor_points(model, ct_spacing, rng)
    cp, cn = model.points[ct], model.normals[ct]
    angles = np.arange(turns) * (2.0 * np.pi / turns)
    spin = rigid.axis_angle(cn[:, None, :], angles[None, :])                # (J, T, 3, 3)
    first = x[rng.choice(len(x), min(first_points, len(x)), replace=False)]
    second = x[rng.choice(len(x), min(second_points, len(x)), replace=False)]
    per_run = max(1, -(-4 * keep // (2 * len(chosen))))
    kept_r, kept_t = [], []
    total = 0
    progress = progress or Progress(quiet=True)
    with progress.stage("pose search", total=2 * len(chosen)) as advance:
        for a in chosen:
            for sign in (1.0, -1.0):
                tilt = rigid.align_vectors(sign * target.normals[a], cn)     # (J, 3, 3)
                rot = (spin @ tilt[:, None]).reshape(-1, 3, 3)
                trans = np.repeat(cp, turns, axis=0) - rot @ x[a]
                s = score_poses(model, rot, trans, first, tau)
                best = np.argpartition(-s, min(per_run, len(s) - 1))[:per_run]
                kept_r.append(rot[best])
                kept_t.append(trans[best])
                total += len(s)
                advance(1)
    rot, trans = np.concatenate(kept_r), np.concatenate(kept_t)
    s = score_poses(model, rot, trans, second, tau)
    order = np.argsort(-s, kind="stable")[:keep]
    return Candidates(rot[order], trans[order], s[order], hypotheses=total)


def distinct(transforms: np.ndarray, points: np.ndarray, min_mm: float, limit: int) -> np.ndarray:
    """Indices of up to ``limit`` poses ``(K, 4, 4)`` (in the given order, best first) that each
    move ``points`` ``(P, 3)`` by a mean of more than ``min_mm`` from every pose kept before them."""
    kept: list[int] = []
    placed = np.einsum("kij,pj->kpi", transforms[:, :3, :3], points) + transforms[:, None, :3, 3]
    for i in range(len(transforms)):
        if kept and np.linalg.norm(placed[kept] - placed[i], axis=2).mean(axis=1).min() <= min_mm:
            continue
        kept.append(i)
        if len(kept) == limit:
            break
    return np.asarray(kept, dtype=np.intp)
