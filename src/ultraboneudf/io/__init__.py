"""Reading point clouds and meshes, writing meshes, points and JSON atomically, validating input.

Point clouds are in millimetres, as ``(N, 3)`` float64 arrays. Readers are chosen by extension
(:data:`POINT_READERS`); every problem with a file is an :class:`~ultraboneudf.errors.InputError`
whose message names the file. Writers never leave a half-written file: they write a temporary file
beside the target and rename it.
"""

from .files import atomic_write_bytes, save_json, sha256_file, sigterm_raises, write_temp
from .meshes import MESH_SUFFIXES, check_mesh_path, load_mesh, save_mesh
from .points import (MAX_COORDINATE_MM, MAX_PLY_VERTICES, MIN_POINTS, PLAUSIBLE_EXTENT_MM, POINT_READERS,
                     POINT_SUFFIXES, check_units, encode_points, load_points, load_sweep_columns,
                     validate_points)
from .sidecar import (FREE_SPACE_BYTES, check_json_output, check_outputs, legacy_sidecar, read_sidecar,
                      save_mesh_with_sidecar, sidecar_path)

__all__ = ["FREE_SPACE_BYTES", "MAX_COORDINATE_MM", "MAX_PLY_VERTICES", "MESH_SUFFIXES", "MIN_POINTS",
           "PLAUSIBLE_EXTENT_MM", "POINT_READERS", "POINT_SUFFIXES", "atomic_write_bytes", "check_mesh_path",
           "check_json_output", "check_outputs", "check_units", "encode_points", "legacy_sidecar", "load_mesh",
           "load_points", "load_sweep_columns", "read_sidecar", "save_json", "save_mesh", "save_mesh_with_sidecar",
           "sha256_file", "sidecar_path", "sigterm_raises", "validate_points", "write_temp"]
