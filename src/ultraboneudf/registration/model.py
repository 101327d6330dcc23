"""The CT bone prepared for registration: dense surface samples with their outward normals, a
KD-tree over them, and a distance field on a regular grid for fast scoring (mm, the CT's frame).

The field holds the unsigned distance (mm) from each grid node to the CT surface, for nodes within
``margin`` of the bone's bounding box; beyond the grid a point counts as ``margin`` away (every
cost that reads the field is truncated below that). It is built with one Euclidean distance
transform: each grid cell that holds a surface sample keeps one of them, the transform finds every
node's nearest such cell, and the node's value is its distance to that cell's sample. That
overestimates the true distance by at most about half a cell, which the search tolerates; the final
refinement measures against the samples themselves (KD-tree), not the grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from ..errors import InputError
from ..geometry.neighbors import KDTree, kd_tree


@dataclass
class BoneModel:
    """A CT bone surface ready to be scored against (all in mm, the CT's frame).

    ``points`` ``(S, 3)``, ``normals`` ``(S, 3)``: area-uniform surface samples and the outward unit
    normals of their faces; ``tree``: KD-tree over ``points``; ``origin`` ``(3,)``, ``spacing``
    (mm), ``field`` ``(X, Y, Z)`` float32: the distance grid (node ``i, j, k`` at
    ``origin + spacing·(i, j, k)``); ``margin``: the grid's reach beyond the bounding box and the
    value of points beyond it; ``area``: the surface area (mm²); ``diagonal``: of the bounding box.
    """

    points: np.ndarray
    normals: np.ndarray
    tree: KDTree
    origin: np.ndarray
    spacing: float
    field: np.ndarray
    margin: float
    area: float
    diagonal: float

    @property
    def centre(self) -> np.ndarray:
        """Centre ``(3,)`` of the samples' bounding box (mm)."""
        return (self.points.min(axis=0) + self.points.max(axis=0)) / 2.0

    def grid_coordinates(self, points: np.ndarray) -> np.ndarray:
        """``points`` ``(…, 3)`` (mm) in grid units (node ``i, j, k`` at ``(i, j, k)``)."""
        return (points - self.origin) / self.spacing

    def lookup(self, grid: np.ndarray) -> np.ndarray:
        """Field value (mm) at the node nearest each grid coordinate ``(…, 3)``; the grid's border
        nodes all hold ``margin``, so coordinates beyond the grid are clipped onto them."""
        shape = self.field.shape
        i = np.clip(np.rint(grid[..., 0]), 0, shape[0] - 1).astype(np.intp)
        j = np.clip(np.rint(grid[..., 1]), 0, shape[1] - 1).astype(np.intp)
        k = np.clip(np.rint(grid[..., 2]), 0, shape[2] - 1).astype(np.intp)
        return self.field.reshape(-1)[(i * shape[1] + j) * shape[2] + k]

    def distance_gradient(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear field value ``(…)`` (mm) and its gradient ``(…, 3)`` at ``points`` ``(…, 3)``
        (mm); points beyond the grid read its border (``margin``, gradient zero)."""
        shape = np.asarray(self.field.shape)
        u = np.clip(self.grid_coordinates(points), 0, shape - 1)
        base = np.minimum(np.floor(u), shape - 2).astype(np.intp)
        f = u - base
        flat = self.field.reshape(-1)
        sy, sx = shape[2], shape[1] * shape[2]
        i0 = base[..., 0] * sx + base[..., 1] * sy + base[..., 2]
        c = [flat[i0 + dx * sx + dy * sy + dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)]
        fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
        # interpolate along z, then y, then x, keeping the partial derivatives
        c00, c01 = c[0] + (c[1] - c[0]) * fz, c[2] + (c[3] - c[2]) * fz
        c10, c11 = c[4] + (c[5] - c[4]) * fz, c[6] + (c[7] - c[6]) * fz
        c0, c1 = c00 + (c01 - c00) * fy, c10 + (c11 - c10) * fy
        value = c0 + (c1 - c0) * fx
        gy = (c01 - c00) + ((c11 - c10) - (c01 - c00)) * fx
        dz0 = (c[1] - c[0]) + ((c[3] - c[2]) - (c[1] - c[0])) * fy
        dz1 = (c[5] - c[4]) + ((c[7] - c[6]) - (c[5] - c[4])) * fy
        grad = np.stack([c1 - c0, gy, dz0 + (dz1 - dz0) * fx], axis=-1) / self.spacing
        return value, grad


def grid_spacing(diagonal: float) -> float:
    """Grid spacing (mm) for a bone whose bounding box has this diagonal: 1/150 of it, kept
    within 1–3 mm (a talus at 1 mm, a pelvis at 2.5 mm, a whole femur at 3 mm)."""
    return float(np.clip(diagonal / 150.0, 1.0, 3.0))


def prepare_bone(mesh: trimesh.Trimesh, margin: float = 20.0, spacing: float | None = None,
                 seed: int = 0, source: str = "CT") -> BoneModel:
    """Sample the CT surface (a closed or open triangle mesh in mm) and build its distance grid.

    ``margin`` (mm): how far beyond the bounding box the grid reaches; ``spacing`` (mm): grid step
    (default :func:`grid_spacing`); samples are about ``spacing / 3`` apart, so each surface cell
    holds several. Raises :class:`InputError` naming ``source`` for a mesh without area.
    """
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0.0:
        raise InputError(f"{source}: the mesh has no area")
    lo, hi = mesh.bounds
    diagonal = float(np.linalg.norm(hi - lo))
    h = grid_spacing(diagonal) if spacing is None else float(spacing)
    n = int(np.clip(area / (h / 3.0) ** 2, 20_000, 400_000))
    points, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    normals = np.asarray(mesh.face_normals)[faces]
    origin = lo - margin
    dims = np.ceil((hi + margin - origin) / h).astype(int) + 1
    cell = np.rint((points - origin) / h).astype(np.intp)
    flat = np.ravel_multi_index(cell.T, dims)
    # one sample per occupied cell: the one seen first (the samples' order is seeded)
    owner = np.full(int(np.prod(dims)), -1, dtype=np.intp)
    owner[flat[::-1]] = np.arange(len(flat))[::-1]
    empty = (owner < 0).reshape(dims)
    nearest_cell = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
    nearest_flat = np.ravel_multi_index(tuple(nearest_cell.reshape(3, -1)), dims)
    del nearest_cell
    nodes = np.indices(dims).reshape(3, -1).T * h + origin
    field = np.linalg.norm(nodes - points[owner[nearest_flat]], axis=1)
    field = np.minimum(field, margin).astype(np.float32).reshape(dims)
    for axis in range(3):  # the border reads as "far" for every clipped lookup
        np.moveaxis(field, axis, 0)[[0, -1]] = margin
    return BoneModel(points=points, normals=normals, tree=kd_tree(points), origin=origin, spacing=h,
                     field=field, margin=float(margin), area=area, diagonal=diagonal)
