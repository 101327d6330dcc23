"""Mesh extraction from unsigned distance fields.

:func:`extract_mesh` dispatches on ``ExtractConfig.mode``: ``faithful`` runs DualMesh-UDF exactly as
the reference (:func:`dualmesh_udf`), ``clean`` a one-layer, edge-manifold variant
(:func:`clean_udf_mesh`); the grid extractors of the baselines (``marching.py``): ``capudf_mc``
(CAP-UDF, §3.5), ``sdf_mc`` (FUNSR, §4.5) and ``udf2sdf`` (CarotidUDF, §5.4). All return a unit-space
``trimesh.Trimesh`` or ``None`` (no mesh).
"""

from __future__ import annotations

import numpy as np
import trimesh

from ..config import CleanConfig, ExtractConfig, GridConfig, check_choices, choices
from ..errors import InputError
from ..fields.base import Field
from ..progress import QUIET, Progress
from .marching import (capudf_marching_cubes, sdf_marching_cubes, udf_to_sdf_marching_cubes)
from .dualmesh import CORNER, EDGE, PLANE, TYPE_NAMES, band_threshold, clean_udf_mesh, dualmesh_udf
from .quality import mesh_quality
from .trim import grazing_faces, trim_to_support, without_faces

MODES: tuple[str, ...] = choices(ExtractConfig, "mode")


def _grid_box(cfg: ExtractConfig, grid: GridConfig, surface: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The grid's box: ``domain``³, or the surface's bounding box enlarged by ``box_margin``."""
    if grid.box == "domain":
        return np.full(3, cfg.domain[0], float), np.full(3, cfg.domain[1], float)
    if grid.box == "surface":
        if surface is None or not len(surface):
            raise InputError("grid.box=surface needs the surface points; this method provides none "
                             "(use --set grid.box=domain)")
        return surface.min(axis=0) - grid.box_margin, surface.max(axis=0) + grid.box_margin
    raise AssertionError(grid.box)  # check_choices admits no other value


def extract_mesh(field: Field, cfg: ExtractConfig, progress: Progress = QUIET, *,
                 surface: np.ndarray | None = None, normals: np.ndarray | None = None,
                 clean: CleanConfig | None = None, grid: GridConfig | None = None) -> trimesh.Trimesh | None:
    """Extract a mesh of the zero set of ``field`` with the extractor chosen by ``cfg.mode``, with
    its own options: ``cfg`` (the DualMesh-UDF octree and vertex thresholds), ``clean`` (the
    edge-crossing extractor's) or ``grid`` (the grid extractors'); ``None``: the defaults.

    ``surface`` (N, 3) and ``normals`` (N, 3), unit space, are the method's hints for the grid
    extractors that need them (``grid.box = surface``, ``grid.far``, ``grid.udf2sdf = normal-sign``).
    Returns the mesh in the field's coordinates, or ``None`` when there is no surface."""
    check_choices(cfg)
    if cfg.mode == "faithful":
        return dualmesh_udf(field, cfg, progress)
    if cfg.mode == "clean":
        return clean_udf_mesh(field, cfg, progress, clean)
    grid = GridConfig() if grid is None else grid
    check_choices(grid)
    if grid.resolution < 2:
        raise InputError(f"grid.resolution must be at least 2, got {grid.resolution}")
    if cfg.mode == "capudf_mc":
        lo, hi = _grid_box(cfg, grid, surface)
        return capudf_marching_cubes(field, lo, hi, grid.resolution, grid.cell_threshold, cfg.batch, progress,
                                     surface=surface, far=grid.far)
    if cfg.mode == "sdf_mc":
        return sdf_marching_cubes(field, grid.resolution, tuple(cfg.domain), cfg.batch, progress)
    if cfg.mode == "udf2sdf":
        return udf_to_sdf_marching_cubes(field, grid.udf2sdf, grid.resolution, tuple(cfg.domain), surface,
                                         normals, project=grid.udf2sdf_project, threshold=grid.cell_threshold,
                                         batch=cfg.batch, progress=progress)
    raise AssertionError(cfg.mode)  # check_choices admits no other value


__all__ = ["extract_mesh", "dualmesh_udf", "clean_udf_mesh", "capudf_marching_cubes", "sdf_marching_cubes",
           "udf_to_sdf_marching_cubes", "mesh_quality", "trim_to_support", "grazing_faces", "without_faces",
           "band_threshold", "MODES", "CORNER", "EDGE", "PLANE", "TYPE_NAMES"]
