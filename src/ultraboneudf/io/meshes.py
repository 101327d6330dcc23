"""Triangle meshes in and out (mm, as given: never altered on reading). A mesh is checked before it
is used: it holds what its header declares, every vertex is finite and every face names vertices
that exist."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from .files import atomic_write_bytes
from .inputs import check_fits_memory, check_input
from .ply import check_ply_length, read_ply_header

if TYPE_CHECKING:
    import trimesh

MESH_SUFFIXES = (".ply", ".obj", ".stl")
"""The mesh formats written (``.off`` is also read)."""
READ_SUFFIXES = (*MESH_SUFFIXES, ".off")


def read_mesh(path: str | os.PathLike) -> "trimesh.Trimesh | None":
    """Read a triangle mesh (``.ply``, ``.obj``, ``.stl``, ``.off``) without altering it; ``None``
    when it is a sound file holding no triangles. :class:`InputError` naming the file when it is
    missing, not a regular file, not a mesh, shorter than its header declares, or has a vertex
    that is NaN or infinite or a face naming a vertex it lacks."""
    path = check_input(path, "mesh file")
    if path.suffix.lower() not in READ_SUFFIXES:
        raise InputError(f"{path}: unknown mesh extension {path.suffix!r}; use one of {', '.join(READ_SUFFIXES)}")
    # trimesh holds several copies while it parses: refuse a file that cannot fit before it starts
    check_fits_memory(path, 6 * path.stat().st_size, "its triangles")
    if path.suffix.lower() == ".ply":
        check_ply_length(path, read_ply_header(path))
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        return None
    bad = ~np.isfinite(mesh.vertices).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} vertices are NaN or infinite (first: vertex "
                         f"{int(np.flatnonzero(bad)[0])}); the mesh cannot be measured or drawn")
    faces = np.asarray(mesh.faces)
    if faces.min() < 0 or faces.max() >= len(mesh.vertices):
        raise InputError(f"{path}: a face names vertex {int(faces.max() if faces.max() >= len(mesh.vertices) else faces.min())}"
                         f" of {len(mesh.vertices)}; the file is damaged")
    return mesh


def load_mesh(path: str | os.PathLike) -> "trimesh.Trimesh":
    """Read a triangle mesh as :func:`read_mesh` does; a mesh without triangles is an error too."""
    mesh = read_mesh(path)
    if mesh is None:
        raise InputError(f"{path}: holds no triangles")
    return mesh


def check_mesh_path(path: str | os.PathLike) -> Path:
    """Return ``path`` as a Path if its suffix is a mesh format we write, else raise InputError."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: unknown mesh extension {path.suffix!r}; "
                         f"use one of {', '.join(MESH_SUFFIXES)}")
    return path


def mesh_bytes(mesh: "trimesh.Trimesh", path: str | os.PathLike) -> bytes:
    """The bytes of ``mesh`` in the format of ``path``'s suffix (``.ply`` binary, ``.obj``, ``.stl``)."""
    import trimesh

    path = check_mesh_path(path)
    data = trimesh.exchange.export.export_mesh(mesh, file_obj=None, file_type=path.suffix[1:].lower())
    return data if isinstance(data, bytes) else data.encode("utf-8")


def save_mesh(mesh: "trimesh.Trimesh", path: str | os.PathLike) -> None:
    """Write a mesh atomically; the format follows the suffix (``.ply`` binary, ``.obj``, ``.stl``)."""
    atomic_write_bytes(path, mesh_bytes(mesh, path))
