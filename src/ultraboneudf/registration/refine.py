"""Local refinement of poses (target → CT, mm): many candidates at once in the distance field, then
the chosen one by trimmed point-to-plane ICP against the CT's surface samples.

Both minimise a robust sum over target points of the squared distance to the CT surface, with
Tukey's biweight ``w = (1 − (d/c)²)²`` for ``d < c`` and 0 beyond: a point the CT cannot explain
(farther than ``c``) has no say, so clusters and sheets of false echoes do not pull the bone. ``c``
shrinks over the iterations (a schedule of cut-offs in mm): wide at first, so that a pose some
millimetres off still sees its points, tight at the end, so that the residual is measured on the
bone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import rigid
from .model import BoneModel
from .search import Candidates, soft_inliers


def _schedule(cutoffs: tuple[float, ...], iterations: int) -> list[float]:
    """``iterations`` cut-offs stepping through ``cutoffs`` in equal runs."""
    return [cutoffs[min(i * len(cutoffs) // iterations, len(cutoffs) - 1)] for i in range(iterations)]


def _step(jac: np.ndarray, residual: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Gauss–Newton steps ``(K, 6)`` (rotation vector, translation) of weighted least squares
    ``Σ w (r + J δ)²`` for ``K`` problems at once: ``jac`` ``(K, M, 6)``, ``residual``, ``weight`` ``(K, M)``."""
    h = np.einsum("kmi,kmj,km->kij", jac, jac, weight) + 1e-6 * np.eye(6)
    g = np.einsum("kmi,km->ki", jac, weight * residual)
    return -np.linalg.solve(h, g[..., None])[..., 0]


def _compose(rotation: np.ndarray, translation: np.ndarray, step: np.ndarray, centre: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Apply the small motions ``step`` ``(K, 6)`` (rotation about ``centre`` ``(K, 3)``, then a
    translation) after the poses ``(K, 3, 3)``, ``(K, 3)``."""
    turn = rigid.rotvec(step[:, :3])
    new_t = np.einsum("kab,kb->ka", turn, translation - centre) + centre + step[:, 3:]
    return turn @ rotation, new_t


def tukey(d: np.ndarray, c: float) -> np.ndarray:
    """Tukey biweight weights of distances ``d`` (mm) for the cut-off ``c`` (mm)."""
    return np.where(d < c, (1.0 - (d / c) ** 2) ** 2, 0.0)


def refine_in_field(model: BoneModel, candidates: Candidates, points: np.ndarray, cutoffs: tuple[float, ...],
                    iterations: int, score_tau: float) -> Candidates:
    """Refine every candidate pose at once by Gauss–Newton on the distance field (``points``
    ``(M, 3)``, target frame); rescored as the soft inlier share at ``score_tau`` mm on the
    trilinear field, best first."""
    rot, trans = candidates.rotation.copy(), candidates.translation.copy()
    for c in _schedule(cutoffs, iterations):
        y = np.einsum("kab,mb->kma", rot, points) + trans[:, None, :]
        d, g = model.distance_gradient(y)
        centre = y.mean(axis=1)
        # d(distance)/d(rotation about the centre) = (y − centre) × ∇d; /d(translation) = ∇d
        jac = np.concatenate([np.cross(y - centre[:, None], g), g], axis=-1)
        rot, trans = _compose(rot, trans, _step(jac, d, tukey(d, c)), centre)
    y = np.einsum("kab,mb->kma", rot, points) + trans[:, None, :]
    score = soft_inliers(model.distance_gradient(y)[0], score_tau).mean(axis=1)
    order = np.argsort(-score, kind="stable")
    return Candidates(rot[order], trans[order], score[order], candidates.hypotheses)


@dataclass
class IcpResult:
    """A refined pose target → CT ``(4, 4)`` and the final distances ``(N,)`` (mm) of the target's
    points to the CT surface samples."""

    transform: np.ndarray
    distances: np.ndarray
    iterations: int


def icp(model: BoneModel, transform: np.ndarray, points: np.ndarray, cutoffs: tuple[float, ...],
        iterations: int, tolerance: float = 1e-3, workers: int = -1) -> IcpResult:
    """Trimmed point-to-plane ICP of ``points`` ``(N, 3)`` (target frame) onto the CT's samples,
    from ``transform`` (target → CT). Each iteration pairs every point with its nearest CT sample
    and minimises ``Σ w (n·(R x + t − p))²`` with Tukey weights at the iteration's cut-off; it stops
    early once the last cut-off is reached and a step moves no point by more than ``tolerance`` mm;
    ``workers``: KD-tree threads (-1: all cores)."""
    rot, trans = transform[None, :3, :3].copy(), transform[None, :3, 3].copy()
    steps = _schedule(cutoffs, iterations)
    reach = float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())
    done = 0
    for i, c in enumerate(steps):
        y = points @ rot[0].T + trans[0]
        # points beyond the cut-off get no weight: the tree need not look farther for them
        d, idx = model.tree.query(y, distance_upper_bound=c, workers=workers)
        near = np.isfinite(d)
        if near.sum() < 6:
            break
        y, d, idx = y[near], d[near], idx[near]
        n = model.normals[idx]
        r = np.einsum("mi,mi->m", y - model.points[idx], n)
        centre = y.mean(axis=0)
        jac = np.concatenate([np.cross(y - centre, n), n], axis=-1)
        step = _step(jac[None], r[None], tukey(d, c)[None])
        rot, trans = _compose(rot, trans, step, centre[None])
        done = i + 1
        moved = np.linalg.norm(step[0, :3]) * reach + np.linalg.norm(step[0, 3:])
        if c == steps[-1] and moved < tolerance:
            break
    final = rigid.homogeneous(rot[0], trans[0])
    d = model.tree.query(rigid.apply(final, points), workers=workers)[0]
    return IcpResult(final, d, done)
