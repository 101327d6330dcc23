"""Mesh extraction from unsigned distance fields.

:func:`extract_mesh` dispatches on ``ExtractConfig.mode``: ``faithful`` runs DualMesh-UDF exactly as
the reference (:func:`dualmesh_udf`), ``clean`` a one-layer, edge-manifold variant
(:func:`clean_udf_mesh`). Both return a unit-space ``trimesh.Trimesh`` or ``None`` (no mesh).
"""

from __future__ import annotations

import trimesh

from ..config import ExtractConfig
from ..errors import InputError
from ..fields.base import Field
from ..progress import QUIET, Progress
from .clean import clean_udf_mesh
from .dualmesh import CORNER, EDGE, PLANE, TYPE_NAMES, band_threshold, dualmesh_udf
from .quality import mesh_quality

MODES = ("faithful", "clean")


def extract_mesh(field: Field, cfg: ExtractConfig, progress: Progress = QUIET) -> trimesh.Trimesh | None:
    """Extract a mesh of the zero set of ``field`` with the extractor chosen by ``cfg.mode``.

    Returns the mesh in the field's coordinates, or ``None`` when there is no surface."""
    if cfg.mode == "faithful":
        return dualmesh_udf(field, cfg, progress)
    if cfg.mode == "clean":
        return clean_udf_mesh(field, cfg, progress)
    raise InputError(f"unknown extraction mode {cfg.mode!r}; choose one of {', '.join(MODES)}")


__all__ = ["extract_mesh", "dualmesh_udf", "clean_udf_mesh", "mesh_quality", "band_threshold", "MODES",
           "CORNER", "EDGE", "PLANE", "TYPE_NAMES"]
