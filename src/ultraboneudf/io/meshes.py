"""Triangle meshes in and out (mm, as given: never altered on reading)."""

from __future__ import annotations

import os
from pathlib import Path

import trimesh

from ..errors import InputError
from .files import atomic_write_bytes

MESH_SUFFIXES = (".ply", ".obj", ".stl")
"""The mesh formats written (``.off`` is also read)."""


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a triangle mesh (``.ply``, ``.obj``, ``.stl``, ``.off``) without altering it."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:
        raise InputError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: holds no triangles")
    return mesh


def check_mesh_path(path: str | os.PathLike) -> Path:
    """Return ``path`` as a Path if its suffix is a mesh format we write, else raise InputError."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: unknown mesh extension {path.suffix!r}; "
                         f"use one of {', '.join(MESH_SUFFIXES)}")
    return path


def save_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike) -> None:
    """Write a mesh atomically; the format follows the suffix (``.ply`` binary, ``.obj``, ``.stl``)."""
    path = check_mesh_path(path)
    data = trimesh.exchange.export.export_mesh(mesh, file_obj=None, file_type=path.suffix[1:].lower())
    atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode("utf-8"))


