"""Rigid transforms in millimetres: 4×4 matrices, batched rotations, the least-squares fit of
paired points, and the distance between two poses as the displacement of a surface's points."""

from __future__ import annotations

import numpy as np


def homogeneous(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(…, 4, 4)`` matrices from rotations ``(…, 3, 3)`` and translations ``(…, 3)`` (mm)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    out = np.zeros(rotation.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert(transform: np.ndarray) -> np.ndarray:
    """Inverse of rigid ``(…, 4, 4)`` transforms (no general matrix inverse: Rᵀ, −Rᵀt)."""
    r = np.swapaxes(transform[..., :3, :3], -1, -2)
    return homogeneous(r, -np.einsum("...ij,...j->...i", r, transform[..., :3, 3]))


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` ``(N, 3)`` mapped by one ``(4, 4)`` transform."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def axis_angle(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rotations ``(…, 3, 3)`` about unit ``axes`` ``(…, 3)`` by ``angles`` ``(…)`` radians
    (Rodrigues' formula; the arrays broadcast)."""
    axes = np.asarray(axes, dtype=np.float64)
    angles = np.asarray(angles, dtype=np.float64)
    shape = np.broadcast_shapes(axes.shape[:-1], angles.shape)
    k = np.broadcast_to(axes, shape + (3,))
    a = np.broadcast_to(angles, shape)[..., None, None]
    kx = np.zeros(shape + (3, 3))
    kx[..., 0, 1], kx[..., 0, 2], kx[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    kx = kx - np.swapaxes(kx, -1, -2)
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)


def rotvec(vectors: np.ndarray) -> np.ndarray:
    """Rotations ``(…, 3, 3)`` of rotation vectors ``(…, 3)`` (axis × angle in radians)."""
    vectors = np.asarray(vectors, dtype=np.float64)
    angle = np.linalg.norm(vectors, axis=-1)
    axis = vectors / np.where(angle > 0, angle, 1.0)[..., None]
    axis[angle == 0] = (1.0, 0.0, 0.0)
    return axis_angle(axis, angle)


def align_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotations ``(…, 3, 3)`` that turn unit vectors ``a`` onto unit vectors ``b``
    (``(…, 3)`` each, broadcast); opposite vectors turn by 180° about an axis normal to ``a``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=-1)
    cos = np.einsum("...i,...i->...", a, b)
    # a normal to a for the degenerate (parallel or opposite) case
    helper = np.where((np.abs(a[..., :1]) < 0.9), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    other = np.cross(a, helper)
    other /= np.linalg.norm(other, axis=-1, keepdims=True)
    small = sin < 1e-9
    axis = np.where(small[..., None], other, axis / np.where(small, 1.0, sin)[..., None])
    return axis_angle(axis, np.arctan2(sin, cos))


def fit_rigid(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The ``(4, 4)`` rigid transform that maps ``source`` ``(N, 3)`` onto ``target`` ``(N, 3)``
    best in weighted least squares (Kabsch; a reflection is never returned). ``N ≥ 3`` points not
    on one line determine it."""
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    cs, ct = w @ source, w @ target
    h = (source - cs).T @ ((target - ct) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return homogeneous(r, ct - r @ cs)


def rotation_angle_deg(rotation: np.ndarray) -> np.ndarray:
    """Angle (degrees) of rotations ``(…, 3, 3)``."""
    trace = np.trace(rotation, axis1=-2, axis2=-1)
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def displacement(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance (mm) ``(…, N)`` that each of ``points`` ``(N, 3)`` moves between transforms ``a``
    and ``b`` (``(…, 4, 4)``, broadcast): how far apart two poses put a surface."""
    pa = np.einsum("...ij,nj->...ni", a[..., :3, :3], points) + a[..., None, :3, 3]
    pb = np.einsum("...ij,nj->...ni", b[..., :3, :3], points) + b[..., None, :3, 3]
    return np.linalg.norm(pa - pb, axis=-1)


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` rotations ``(n, 3, 3)`` uniform on SO(3) (normalised Gaussian quaternions)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return quaternion_matrix(q)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotations ``(…, 3, 3)`` of unit quaternions ``(…, 4)`` ordered ``(w, x, y, z)``."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)
