"""Reading point clouds and meshes, writing outputs whole or not at all, validating input.

Point clouds are in millimetres, as ``(N, 3)`` float64 arrays. Readers are chosen by extension
(:data:`POINT_READERS`); every problem with a file is an :class:`~ultraboneudf.errors.InputError`
whose message names the file. Outputs follow one contract (:mod:`.outputs`): never an input, never a
file this package did not write, every result put in place as a unit (:mod:`.commit`).

The names below are imported on first use: checking a file before any work loads neither trimesh
nor PyTorch.
"""

from .._lazy import lazy_getattr

_WHERE = {
    "atomic_write_bytes": "files", "save_json": "files", "sha256_file": "files",
    "Commit": "commit", "WriteError": "commit", "signals_deferred": "commit",
    "check_input": "inputs", "available_memory": "inputs",
    "MESH_SUFFIXES": "meshes", "check_mesh_path": "meshes", "load_mesh": "meshes", "read_mesh": "meshes",
    "mesh_bytes": "meshes", "save_mesh": "meshes",
    "MAX_COORDINATE_MM": "points", "MIN_POINTS": "points", "PLAUSIBLE_EXTENT_MM": "points",
    "POINT_READERS": "points", "POINT_SUFFIXES": "points", "check_units": "points", "encode_points": "points",
    "load_points": "points", "load_sweep_columns": "points", "validate_points": "points",
    "MAX_PLY_VERTICES": "ply",
    "FOLDER_RECORD": "outputs", "FREE_SPACE_BYTES": "outputs", "check_output": "outputs",
    "legacy_sidecar": "outputs", "read_record": "outputs", "record": "outputs", "sidecar_path": "outputs",
    "write_folder_output": "outputs", "write_output": "outputs", "write_outputs": "outputs",
    "check_outputs": "sidecar", "read_sidecar": "sidecar", "save_mesh_with_sidecar": "sidecar",
}

__all__ = sorted(_WHERE)

__getattr__ = lazy_getattr(__name__, _WHERE, globals())


def __dir__() -> list[str]:
    return __all__
