"""The JSON sidecar beside every output mesh, and the checks that a mesh output replaces nothing of
the user's: a mesh and its sidecar are written as a pair or not at all (:mod:`.outputs` holds the
rules every output follows)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

from .meshes import check_mesh_path, mesh_bytes
from .outputs import FREE_SPACE_BYTES, check_output, legacy_sidecar, read_record, sidecar_path, write_output

if TYPE_CHECKING:
    import trimesh

__all__ = ["FREE_SPACE_BYTES", "check_outputs", "legacy_sidecar", "read_sidecar", "save_mesh_with_sidecar",
           "sidecar_path"]


def read_sidecar(path: str | os.PathLike) -> dict[str, Any] | None:
    """The sidecar at ``path`` if this package wrote it, else ``None`` (missing, unreadable, or
    someone else's file)."""
    return read_record(path)


def check_outputs(mesh_path: str | os.PathLike, inputs: Iterable[str | os.PathLike] = (),
                  overwrite: bool = False) -> Path:
    """Check, before any work, that writing ``mesh_path`` and its sidecar loses nothing
    (:func:`~ultraboneudf.io.outputs.check_output`): neither is an input nor inside an input
    folder; an existing mesh is replaced only as an unchanged earlier output of this package
    (under either sidecar name), an existing sidecar only if this package wrote it for this mesh
    (``overwrite``: replaced anyway); the folder is writable and has room. Raises
    :class:`~ultraboneudf.errors.InputError` naming the file; returns ``mesh_path`` as a :class:`Path`."""
    return check_output(check_mesh_path(mesh_path), inputs=inputs, overwrite=overwrite)


def save_mesh_with_sidecar(mesh: "trimesh.Trimesh", path: str | os.PathLike, sidecar: dict[str, Any], *,
                           overwrite: bool = False, remove: Iterable[str | os.PathLike] = ()) -> Path:
    """Write the mesh (format by suffix) and its sidecar (:func:`sidecar_path`, with the mesh's
    name and SHA-256) as a unit (:class:`~ultraboneudf.io.commit.Commit`): on any failure or
    signal either both new files or the earlier pair are there. An earlier version's sidecar of
    the mesh replaced (``NAME.json``) and the files in ``remove`` (a finished run's checkpoint) go
    in the same commit. Returns the sidecar path."""
    path = check_mesh_path(path)
    legacy = legacy_sidecar(path)
    meta = {"written_by": "ultraboneudf", **sidecar, "mesh": path.name}
    write_output(path, mesh_bytes(mesh, path), meta, overwrite=overwrite,
                 remove=[*([legacy] if legacy is not None else []), *remove])
    return sidecar_path(path)
