"""The pixel → world chain: rigid transforms, Euler angles, pixel scaling, rigidity checks.

All matrices are 4×4 homogeneous, acting on column vectors, lengths in millimetres (pixels where a
matrix maps pixel indices). Euler angles follow the UltraBones100k convention: extrinsic ``xyz`` in
degrees (``scipy.spatial.transform.Rotation.from_euler('xyz', angles, degrees=True)``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError

RIGID_TOL = 1e-4
"""Largest accepted deviation of ``RᵀR`` from the identity (and of ``det R`` from 1)."""


def rigid_from_euler(translation_mm: Sequence[float], euler_xyz_deg: Sequence[float]) -> np.ndarray:
    """4×4 rigid transform from a translation (mm) and extrinsic-xyz Euler angles (degrees)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", np.asarray(euler_xyz_deg, dtype=np.float64),
                                      degrees=True).as_matrix()
    out[:3, 3] = np.asarray(translation_mm, dtype=np.float64)
    return out


def euler_from_rigid(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`rigid_from_euler`: ``(translation_mm (3,), euler_xyz_deg (3,))``."""
    m = np.asarray(matrix, dtype=np.float64)
    return m[:3, 3].copy(), Rotation.from_matrix(m[:3, :3]).as_euler("xyz", degrees=True)


def pixel_to_image_matrix(spacing_mm: Sequence[float], pixel_offset: float) -> np.ndarray:
    """4×4 map from pixel indices ``[c, r, 0, 1]`` to image-plane mm ``[(c+o)·sx, (r+o)·sy, 0, 1]``."""
    sx, sy = float(spacing_mm[0]), float(spacing_mm[1])
    out = np.diag([sx, sy, 1.0, 1.0])
    out[0, 3] = pixel_offset * sx
    out[1, 3] = pixel_offset * sy
    return out


def invert_rigid(matrix: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform (``Rᵀ``, ``−Rᵀt``), exact to rounding."""
    m = np.asarray(matrix, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def rigidity_error(matrix: np.ndarray) -> float:
    """``max(|RᵀR − I|, |det R − 1|, |last row − [0,0,0,1]|)`` of a 4×4 matrix (0 for rigid)."""
    m = np.asarray(matrix, dtype=np.float64)
    rot = m[:3, :3]
    err = np.abs(rot.T @ rot - np.eye(3)).max()
    err = max(err, abs(np.linalg.det(rot) - 1.0))
    return float(max(err, np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max()))


def check_rigid(matrix: np.ndarray, source: str, tol: float = RIGID_TOL) -> np.ndarray:
    """Return ``matrix`` as a 4×4 float64 array if it is a finite rigid transform.

    Raises :class:`InputError` naming ``source`` for a wrong shape, NaN/Inf, a scaled, sheared or
    mirrored rotation part (``|RᵀR − I| > tol`` or ``det R < 0``), or a projective last row.
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: the transform is not numeric") from None
    if m.shape != (4, 4):
        raise InputError(f"{source}: expected a 4×4 transform, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise InputError(f"{source}: the transform contains NaN or Inf")
    err = rigidity_error(m)
    if err > tol:
        det = np.linalg.det(m[:3, :3])
        kind = "mirrored (det < 0)" if det < 0 else "scaled or sheared"
        raise InputError(f"{source}: the transform is not rigid ({kind}; deviation {err:.3g} from a "
                         f"rotation + translation, tolerance {tol:g})")
    return m


def split_scaled_transform(matrix: np.ndarray, source: str,
                           tol: float = RIGID_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Split a pixel → world matrix (PLUS ``ImageToReference``) into ``(rigid 4×4, spacing (2,))``.

    The first two columns carry the pixel size: ``sx = |col 0|``, ``sy = |col 1|`` (mm per pixel).
    The third column (the out-of-plane scale, arbitrary in PLUS calibrations) is ignored and
    replaced by ``x̂ × ŷ``. Raises :class:`InputError` naming ``source`` when a column has zero
    length (no pixel spacing), when the in-plane axes are not perpendicular (shear), or when the
    matrix is not finite/affine.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise InputError(f"{source}: expected a 4×4 transform, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise InputError(f"{source}: the transform contains NaN or Inf")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise InputError(f"{source}: the transform's last row is {m[3].tolist()}, not [0, 0, 0, 1]")
    sx, sy = np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 1])
    scale = max(sx, sy)
    if min(sx, sy) <= 1e-9 * max(1.0, scale):
        raise InputError(f"{source}: no pixel spacing (the transform maps an image axis to zero "
                         f"length: |x| = {sx:.3g}, |y| = {sy:.3g} mm/px)")
    x, y = m[:3, 0] / sx, m[:3, 1] / sy
    if abs(float(x @ y)) > tol:
        raise InputError(f"{source}: the transform is not rigid (image axes sheared: cos angle "
                         f"{float(x @ y):.3g})")
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = x, y, np.cross(x, y)
    out[:3, 3] = m[:3, 3]
    return out, np.array([sx, sy])


def pixels_to_world(pixel_to_world: np.ndarray, cols: np.ndarray, rows: np.ndarray,
                    frame_index: np.ndarray | None = None) -> np.ndarray:
    """Map pixel indices to world mm.

    Args:
        pixel_to_world: ``(4, 4)`` for one frame, or ``(F, 4, 4)`` with ``frame_index``.
        cols, rows: ``(N,)`` pixel column and row indices (may be fractional).
        frame_index: ``(N,)`` int frame of each pixel when ``pixel_to_world`` is ``(F, 4, 4)``.

    Returns:
        ``(N, 3)`` float64 world coordinates in mm.
    """
    c = np.asarray(cols, dtype=np.float64)[:, None]
    r = np.asarray(rows, dtype=np.float64)[:, None]
    m = np.asarray(pixel_to_world, dtype=np.float64)
    if m.ndim == 2:
        return m[:3, 0] * c + m[:3, 1] * r + m[:3, 3]
    if frame_index is None:
        raise ValueError("frame_index is needed with a stack of matrices")
    mi = m[np.asarray(frame_index, dtype=np.int64)]
    return mi[:, :3, 0] * c + mi[:, :3, 1] * r + mi[:, :3, 3]


def format_matrix(matrix: np.ndarray) -> str:
    """16 numbers, row-major, shortest exact representation (round-trips bit for bit)."""
    return " ".join(repr(float(v)) for v in np.asarray(matrix, dtype=np.float64).reshape(16))


def parse_matrix(text: str, source: str) -> np.ndarray:
    """Parse 16 whitespace-separated numbers (row-major) into a 4×4 matrix; errors name ``source``."""
    parts = text.split()
    if len(parts) != 16:
        raise InputError(f"{source}: expected 16 numbers for a 4×4 transform, got {len(parts)}")
    try:
        return np.array([float(p) for p in parts], dtype=np.float64).reshape(4, 4)
    except ValueError:
        raise InputError(f"{source}: cannot parse the transform numbers {text[:80]!r}") from None
