"""Seeded, area-uniform sampling of triangle meshes (docs/ALGORITHMS.md §6.2 steps 1–2).

The sampler only needs vertices and faces, so it accepts anything a reconstruction method returns:
triangle soups (no shared vertices), non-manifold edges, inconsistent orientation, duplicated and
zero-area faces. A face's probability is its area divided by the total area, computed in float64;
zero-area faces and faces that touch a non-finite vertex get weight zero. Inside a face the point is
uniform (barycentric "fold" rule: draw ``u, v`` in [0, 1), reflect when ``u + v > 1``).

Points are returned in face order (faces with more area get proportionally more consecutive rows).
The order carries no meaning; the metrics re-order points spatially before searching them.
"""

from __future__ import annotations

from typing import Any, Union

import numpy as np
import trimesh

from ..errors import InputError

MeshLike = Union[trimesh.Trimesh, tuple[Any, Any]]
"""A :class:`trimesh.Trimesh` or a ``(vertices (V, 3), faces (F, 3))`` pair, coordinates in mm."""

_CHUNK = 1 << 20  # rows per block when building sample coordinates (bounds temporary memory)


class DegenerateMeshError(InputError):
    """A mesh with no faces or no area: nothing can be sampled from it."""


def mesh_arrays(mesh: MeshLike, source: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Return ``(vertices (V, 3) float64, faces (F, 3) int64)`` of ``mesh`` without altering it.

    Raises :class:`InputError` naming ``source`` when the arrays have the wrong shape or a face
    refers to a vertex that does not exist. Non-finite vertices are allowed here (their faces get
    weight zero in :func:`face_areas`).
    """
    if isinstance(mesh, trimesh.Trimesh):
        vertices, faces = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        vertices, faces = mesh
    else:
        raise InputError(f"{source}: expected a trimesh.Trimesh or a (vertices, faces) pair, "
                         f"got {type(mesh).__name__}")
    try:
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
    except (TypeError, ValueError):
        raise InputError(f"{source}: vertices or faces cannot be read as numeric arrays") from None
    if v.size == 0:
        v = v.reshape(0, 3)
    if f.size == 0:
        f = f.reshape(0, 3).astype(np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"{source}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"{source}: faces must have shape (F, 3) (triangles), got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.all(np.mod(f, 1) == 0):
            raise InputError(f"{source}: face indices are not integers")
    f = f.astype(np.int64, copy=False)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        bad = int(f.min()) if f.min() < 0 else int(f.max())
        raise InputError(f"{source}: a face refers to vertex {bad} but the mesh has {len(v)} vertices")
    return v, f


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of every face in mm², ``(F,)`` float64; 0 for degenerate or non-finite faces."""
    a = vertices[faces[:, 0]]
    e1 = vertices[faces[:, 1]] - a
    e2 = vertices[faces[:, 2]] - a
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    area[~np.isfinite(area)] = 0.0
    return area


def surface_area(mesh: MeshLike, source: str = "mesh") -> float:
    """Total area (mm²) of the faces that can be sampled."""
    v, f = mesh_arrays(mesh, source)
    return float(face_areas(v, f).sum()) if len(f) else 0.0


def as_generator(seed: int | np.random.Generator | np.random.SeedSequence | None) -> np.random.Generator:
    """A NumPy generator from an int seed, a SeedSequence or an existing generator."""
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)


def sample_surface(mesh: MeshLike, n: int, seed: int | np.random.Generator | np.random.SeedSequence | None = 0,
                   source: str = "mesh") -> np.ndarray:
    """Draw ``n`` points uniformly by area on ``mesh``; ``(n, 3)`` float64 in the mesh's units (mm).

    The same ``seed`` and mesh give the same points. Face counts are one multinomial draw over the
    area weights, so the work is O(F + n) and no sort is needed. Raises
    :class:`DegenerateMeshError` (an :class:`InputError`) when the mesh has no faces or zero total
    area, and :class:`InputError` for ``n < 1``.
    """
    n = int(n)
    if n < 1:
        raise InputError(f"{source}: the number of samples must be at least 1, got {n}")
    v, f = mesh_arrays(mesh, source)
    if len(f) == 0:
        raise DegenerateMeshError(f"{source}: the mesh has no faces")
    area = face_areas(v, f)
    total = float(area.sum())
    if not total > 0.0:
        raise DegenerateMeshError(f"{source}: the mesh has zero area ({len(f)} degenerate faces)")
    rng = as_generator(seed)
    keep = np.flatnonzero(area > 0.0)
    weights = area[keep] / total
    weights /= weights.sum()  # exact normalisation guards the multinomial's sum(p[:-1]) <= 1 check
    counts = rng.multinomial(n, weights)
    face_of_sample = np.repeat(keep, counts)
    out = np.empty((n, 3), dtype=np.float64)
    for start in range(0, n, _CHUNK):
        stop = min(n, start + _CHUNK)
        tri = f[face_of_sample[start:stop]]
        uv = rng.random((stop - start, 2))
        fold = uv.sum(axis=1) > 1.0
        uv[fold] = 1.0 - uv[fold]
        a = v[tri[:, 0]]
        out[start:stop] = (a + uv[:, :1] * (v[tri[:, 1]] - a) + uv[:, 1:] * (v[tri[:, 2]] - a))
    return out
