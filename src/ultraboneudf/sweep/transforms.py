"""The pixel → world chain: rigid transforms, Euler angles, pixel scaling, rigidity checks.

All matrices are 4×4 homogeneous, acting on column vectors, lengths in millimetres (pixels where a
matrix maps pixel indices). Euler angles follow the UltraBones100k convention: extrinsic ``xyz`` in
degrees (``scipy.spatial.transform.Rotation.from_euler('xyz', angles, degrees=True)``).
"""

from __future__ import annotations

from dataclasses import dataclass
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


def pixel_to_image_matrix(spacing_mm: Sequence[float], pixel_offset: float,
                          shear_deg: float = 0.0) -> np.ndarray:
    """4×4 map from pixel indices ``[c, r, 0, 1]`` to image-plane mm.

    Without shear: ``[(c+o)·sx, (r+o)·sy, 0, 1]``. A calibration whose image axes are not exactly
    perpendicular (PLUS calibrations: up to a few degrees) has the row axis tilted by ``φ =
    shear_deg`` toward the column axis: ``x = (c+o)·sx + (r+o)·sy·sin φ``, ``y = (r+o)·sy·cos φ``,
    so ``sx`` and ``sy`` stay the lengths of one pixel step along each image axis.
    """
    sx, sy = float(spacing_mm[0]), float(spacing_mm[1])
    phi = np.radians(float(shear_deg))
    out = np.eye(4)
    out[0, 0], out[0, 1], out[1, 1] = sx, sy * np.sin(phi), sy * np.cos(phi)
    out[:2, 3] = out[:2, :2] @ [pixel_offset, pixel_offset]
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
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise InputError(f"{source}: the transform's last row must be 0 0 0 1, got {m[3].tolist()}")
    err = rigidity_error(m)
    if err > tol:
        det = np.linalg.det(m[:3, :3])
        kind = "mirrored (det < 0)" if det < 0 else "scaled or sheared"
        raise InputError(f"{source}: the transform is not rigid ({kind}; deviation {err:.3g} from a "
                         f"rotation + translation, tolerance {tol:g})")
    return m


MAX_SHEAR_DEG = 5.0
"""Largest accepted angle between a calibration's image axes and a right angle, after the
per-axis pixel scale is removed. Real freehand calibrations are a little sheared (PlusLibData:
0.9° and 2.7°); a larger angle means a wrong matrix, not a calibration error."""


@dataclass(frozen=True)
class PixelTransform:
    """A pixel → mm affine matrix split into a rigid part, pixel spacing and shear.

    ``matrix = rigid · pixel_to_image_matrix(spacing_mm, 0, shear_deg)`` on the image plane
    (``z = 0``); ``out_of_plane_deg`` is how far the matrix's third column is from the image
    normal (it does not act on pixels, so it is only reported).
    """

    rigid: np.ndarray
    spacing_mm: np.ndarray
    shear_deg: float
    out_of_plane_deg: float


def _angle_from_right(u: np.ndarray, v: np.ndarray) -> float:
    """Degrees by which the angle between ``u`` and ``v`` differs from 90°."""
    c = float(u @ v) / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arcsin(min(1.0, abs(c)))))


def decompose_pixel_transform(matrix: np.ndarray, source: str,
                              max_shear_deg: float = MAX_SHEAR_DEG) -> PixelTransform:
    """Split a pixel → mm matrix (a PLUS ``ImageToProbe`` calibration or an ``ImageToReference``
    pose) into rigid part, per-axis pixel spacing and shear.

    The first two columns carry the pixel size (``sx = |col 0|``, ``sy = |col 1|``, mm per pixel,
    possibly different). The rigid part has ``x̂ = col 0 / sx``, ``ŷ`` the unit part of col 1
    perpendicular to ``x̂`` and ``ẑ = x̂ × ŷ``; the shear is the angle between col 0 and col 1 minus
    90°. The third column (out-of-plane scale, arbitrary in PLUS calibrations) does not act on
    pixels; only a mirror (it pointing against ``x̂ × ŷ``) is an error.

    Raises :class:`InputError` naming ``source`` for a wrong shape, NaN/Inf, a projective last row,
    a zero-length image axis (no pixel spacing), a mirrored matrix, or shear beyond
    ``max_shear_deg``.
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        raise InputError(f"{source}: expected a 4×4 transform, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise InputError(f"{source}: the transform contains NaN or Inf")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOL:
        raise InputError(f"{source}: the transform's last row is {m[3].tolist()}, not [0, 0, 0, 1]")
    a0, a1, a2 = m[:3, 0], m[:3, 1], m[:3, 2]
    sx, sy = float(np.linalg.norm(a0)), float(np.linalg.norm(a1))
    if min(sx, sy) <= 1e-9 * max(1.0, sx, sy):
        raise InputError(f"{source}: no pixel spacing (the transform maps an image axis to zero "
                         f"length: |x| = {sx:.3g}, |y| = {sy:.3g} mm/px)")
    x = a0 / sx
    y = a1 - (a1 @ x) * x
    if np.linalg.norm(y) <= 1e-9 * sy:
        raise InputError(f"{source}: the image axes are parallel (not a pixel → mm transform)")
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    shear = float(np.degrees(np.arctan2(a1 @ x, a1 @ y)))
    if abs(shear) > max_shear_deg:
        raise InputError(f"{source}: the transform is not rigid after removing the pixel scale "
                         f"(image axes sheared by {abs(shear):.2f}°, tolerance {max_shear_deg:g}°)")
    out_of_plane = 0.0
    nz = float(np.linalg.norm(a2))
    if nz > 1e-12:
        if a2 @ z < 0:
            raise InputError(f"{source}: the transform is mirrored (its third column points "
                             f"against x × y; det < 0)")
        out_of_plane = float(np.degrees(np.arccos(min(1.0, float(a2 @ z) / nz))))
        if out_of_plane > max_shear_deg:
            raise InputError(f"{source}: the transform is not rigid after removing the pixel scale "
                             f"(third axis {out_of_plane:.2f}° off the image normal, tolerance "
                             f"{max_shear_deg:g}°)")
    rigid = np.eye(4)
    rigid[:3, 0], rigid[:3, 1], rigid[:3, 2] = x, y, z
    rigid[:3, 3] = m[:3, 3]
    return PixelTransform(rigid, np.array([sx, sy]), shear, out_of_plane)


def split_scaled_transform(matrix: np.ndarray, source: str,
                           tol: float = RIGID_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Split an unsheared pixel → world matrix into ``(rigid 4×4, spacing (2,))``.

    Like :func:`decompose_pixel_transform` but rejects any shear beyond ``tol`` (as the cosine of
    the angle between the image axes): for matrices written by a program, which are exact.
    """
    tol_deg = float(np.degrees(np.arcsin(min(1.0, tol))))
    part = decompose_pixel_transform(matrix, source, max_shear_deg=90.0)
    if abs(part.shear_deg) > tol_deg:
        raise InputError(f"{source}: the transform is not rigid (image axes sheared by "
                         f"{abs(part.shear_deg):.3g}°)")
    return part.rigid, part.spacing_mm


def is_pixel_offset(matrices: np.ndarray, tol: float = 1e-9) -> bool:
    """True if every matrix of ``(F, 4, 4)`` (or one 4×4) is the same pure in-plane translation:
    what a crop or pad between two pixel frames looks like (``ImageToCroppedImage``), never a pose."""
    m = np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4)
    if not np.isfinite(m).all() or np.abs(m - m[0]).max() > tol:
        return False
    t = np.eye(4)
    t[:2, 3] = m[0, :2, 3]
    return bool(np.abs(m[0] - t).max() <= tol)


def invert_affine(matrices: np.ndarray) -> np.ndarray:
    """Inverse of one 4×4 or a stack ``(F, 4, 4)`` of affine transforms."""
    return np.linalg.inv(np.asarray(matrices, dtype=np.float64))


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
