"""The JSON sidecar beside every output mesh, and the checks that an output replaces nothing of the
user's: a mesh and its sidecar are written as a pair or not at all."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import trimesh

from ..errors import InputError
from .files import sigterm_raises, write_temp
from .meshes import check_mesh_path


def sidecar_path(mesh_path: str | os.PathLike) -> Path:
    """The JSON sidecar of a mesh file: the mesh's whole name plus ``.json`` (``bone.ply`` →
    ``bone.ply.json``), so that meshes of different formats never share one."""
    path = Path(mesh_path)
    return path.with_name(path.name + ".json")


def legacy_sidecar(mesh_path: str | os.PathLike) -> Path | None:
    """An earlier version's sidecar of ``mesh_path`` (``bone.ply`` → ``bone.json``, a name every
    format shared): its path if this package wrote it and it names this mesh, else ``None``."""
    mesh = Path(mesh_path)
    legacy = mesh.with_suffix(".json")
    meta = read_sidecar(legacy) if legacy.exists() else None
    return legacy if meta is not None and meta.get("mesh") == mesh.name else None


def read_sidecar(path: str | os.PathLike) -> dict[str, Any] | None:
    """The sidecar at ``path`` if it is one this package wrote (a JSON object with ``method``,
    ``config`` and ``version``), else ``None`` (missing, unreadable, or someone else's file)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and {"method", "config", "version"} <= data.keys() else None


FREE_SPACE_BYTES = 64 << 20
"""Refuse to start a run whose output folder has less free space than this."""


def check_outputs(mesh_path: str | os.PathLike, inputs: tuple[str | os.PathLike, ...] = ()) -> Path:
    """Check, before any work, that writing ``mesh_path`` and its sidecar loses nothing: neither is
    an input nor inside an input folder; an existing mesh is replaced only with its own sidecar
    (an earlier output of this package, under either sidecar name, replaced as a unit); an
    existing sidecar only if this package wrote it for this mesh; the folder is writable and has
    room. Raises
    :class:`InputError` naming the file; returns ``mesh_path`` as a :class:`Path`."""
    mesh = check_mesh_path(mesh_path)
    side = sidecar_path(mesh)
    for out in (mesh, side):
        _not_an_input(out, inputs)
    meta = read_sidecar(side) if side.exists() else None
    if side.exists() and meta is None:
        raise InputError(f"{side}: exists and is not a sidecar of ultraboneudf; writing {mesh} would "
                         f"replace it (choose another output name)")
    if meta is not None and meta.get("mesh", mesh.name) != mesh.name:
        raise InputError(f"{side}: is the sidecar of {meta['mesh']}; choose another output name for "
                         f"{mesh.name}")
    if mesh.exists() and meta is None and legacy_sidecar(mesh) is None:
        raise InputError(f"{mesh}: exists and is not an output of ultraboneudf (no sidecar {side.name}); "
                         f"choose another output name or remove it")
    _writable(mesh)
    return mesh


def check_json_output(path: str | os.PathLike, inputs: tuple[str | os.PathLike, ...], kind: str) -> Path:
    """Check, before any work, that writing the JSON record ``path`` loses nothing: it ends in
    ``.json``, is neither an input nor inside an input folder, replaces only an earlier record of
    the same ``kind`` (its ``"kind"`` key), and its folder is writable and has room. Raises
    :class:`InputError` naming the file; returns ``path`` as a :class:`Path`."""
    path = Path(path)
    if path.suffix.lower() != ".json":
        raise InputError(f"{path}: the output must be a .json file")
    _not_an_input(path, inputs)
    if path.is_dir():
        raise InputError(f"{path}: is a folder")
    if path.exists():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            data = None
        if not isinstance(data, dict) or data.get("kind") != kind:
            raise InputError(f"{path}: exists and is not an earlier {kind}; choose another output name "
                             f"or remove it")
    _writable(path)
    return path


def _not_an_input(out: Path, inputs: tuple[str | os.PathLike, ...]) -> None:
    """Raise :class:`InputError` when ``out`` is one of ``inputs`` or inside an input folder."""
    for given in map(Path, inputs):
        if not given.exists():
            continue
        if given.is_dir() and out.resolve().is_relative_to(given.resolve()):
            raise InputError(f"{out}: inside the input folder {given}; write the output elsewhere")
        if out.exists() and out.samefile(given):
            raise InputError(f"{out}: is the input; the input is never overwritten, choose another "
                             f"output name")


def _writable(out: Path) -> None:
    """Raise :class:`InputError` when ``out``'s folder (or its nearest existing parent) cannot be
    written or has less than :data:`FREE_SPACE_BYTES` free."""
    folder = out.parent if out.parent.exists() else next(
        (p for p in out.resolve().parents if p.exists()), Path("."))
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write into {folder} (permission denied)")
    free = shutil.disk_usage(folder).free
    if free < FREE_SPACE_BYTES:
        raise InputError(f"{out}: only {free / 2**20:.0f} MB free in {folder}; need at least "
                         f"{FREE_SPACE_BYTES >> 20} MB")


def save_mesh_with_sidecar(mesh: trimesh.Trimesh, path: str | os.PathLike, sidecar: dict[str, Any]) -> Path:
    """Write the mesh (format by suffix) and its sidecar (:func:`sidecar_path`) as a pair: both go
    to temporary files first, then the mesh and last the sidecar are renamed into place; on any
    failure, a signal (SIGTERM is turned into an exception while this runs) or Ctrl-C, both are
    removed, so a mesh never stands without its sidecar. An earlier version's sidecar of the mesh
    replaced (``NAME.json``) is removed once the pair is in place. Returns the sidecar path."""
    path = check_mesh_path(path)
    side = sidecar_path(path)
    data = trimesh.exchange.export.export_mesh(mesh, file_obj=None, file_type=path.suffix[1:].lower())
    blobs = [(path, data if isinstance(data, bytes) else data.encode("utf-8")),
             (side, (json.dumps({**sidecar, "mesh": path.name}, indent=2) + "\n").encode("utf-8"))]
    temps: list[str] = []
    placed: list[Path] = []
    with sigterm_raises():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            for target, blob in blobs:
                temps.append(write_temp(target, blob))
            for (target, _), tmp in zip(blobs, temps):
                os.replace(tmp, target)
                placed.append(target)
        except BaseException as exc:
            for name in temps:
                Path(name).unlink(missing_ok=True)
            if len(placed) < len(blobs):
                for target in placed:
                    target.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise InputError(f"{path}: cannot write ({exc.strerror or exc}); nothing written") from None
            raise
    legacy = legacy_sidecar(path)
    if legacy is not None:
        legacy.unlink(missing_ok=True)  # it described the mesh just replaced
    return side


