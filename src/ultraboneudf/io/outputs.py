"""What an output may replace: never a file the user gave, never one this package did not write.

Every output carries a record that says this package wrote it:

- a file ``X`` has its JSON sidecar ``X.json`` beside it (a mesh's holds the run's provenance; a
  point cloud's, a picture's, a table's or the metrics' what made them), naming ``X`` and holding
  its SHA-256;
- a folder ``D`` holds ``D/ultraboneudf.json``, listing every file in it with its SHA-256.

An existing output is replaced only when its record is there and the file (or every file of the
folder) is still as this package wrote it; ``overwrite`` replaces it anyway, but never an input,
a folder where a file goes, or a special file. :func:`check_output` runs before any work, and again
with the folders locked just before the new result is put in place
(:func:`~ultraboneudf.io.commit.Commit`).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import stat
from pathlib import Path
from typing import Any, Callable, Iterable

from .._version import __version__
from ..errors import InputError
from .commit import Commit, WriteError, recover

WRITTEN_BY = "ultraboneudf"
FOLDER_RECORD = "ultraboneudf.json"
"""The record inside a folder output."""
FREE_SPACE_BYTES = 64 << 20
"""Refuse to start a run whose output folder has less free space than this."""
_RECORD_MAX_BYTES = 64 << 20


def record(command: str, **fields: Any) -> dict[str, Any]:
    """The fields every record of ours starts with, then ``fields``."""
    return {"written_by": WRITTEN_BY, "version": __version__, "command": command, **fields}


def sidecar_path(path: str | os.PathLike) -> Path:
    """The JSON sidecar of an output file: its whole name plus ``.json`` (``bone.ply`` →
    ``bone.ply.json``), so that outputs of different formats never share one."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def read_record(path: str | os.PathLike) -> dict[str, Any] | None:
    """The JSON object at ``path`` if this package wrote it (``written_by``, or an earlier
    version's mesh sidecar with ``method``, ``config`` and ``version``), else ``None`` (missing, a
    link, unreadable, or someone else's file)."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode) or st.st_size > _RECORD_MAX_BYTES:
            return None
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    ours = data.get("written_by") == WRITTEN_BY or {"method", "config", "version"} <= data.keys()
    return data if ours else None


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _named(meta: dict[str, Any]) -> str | None:
    return meta.get("output", meta.get("mesh"))


def legacy_sidecar(path: str | os.PathLike) -> Path | None:
    """An earlier version's sidecar of the mesh ``path`` (``bone.ply`` → ``bone.json``, a name
    every format shared): its path if this package wrote it and it names this mesh, else ``None``."""
    path = Path(path)
    legacy = path.with_suffix(".json")
    meta = read_record(legacy) if legacy != path else None
    return legacy if meta is not None and meta.get("mesh") == path.name else None


# ------------------------------------------------------------------------------------------------
# what stands at a target


def _special(path: Path) -> str | None:
    """What a non-regular, non-folder file at ``path`` is, or ``None``."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return None
    for test, kind in ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return None


def _file_problem(path: Path) -> str | None:
    """Why the file output ``path`` (with its sidecar) may not be written over: ``None`` when
    nothing is there or what is there is an unchanged output of ours."""
    side = sidecar_path(path)
    exists = os.path.lexists(path)
    meta = read_record(side) if os.path.lexists(side) else None
    if os.path.lexists(side) and meta is None:
        return f"{side}: exists and is not a sidecar of ultraboneudf; writing {path.name} would replace it"
    if meta is not None and _named(meta) not in (None, path.name):
        return f"{side}: is the sidecar of {_named(meta)}, not of {path.name}"
    if not exists:
        return None
    if path.is_symlink() or not path.is_file():
        return f"{path}: exists and is {'a link' if path.is_symlink() else 'not a file'}, not an output of ultraboneudf"
    if meta is None:
        if legacy_sidecar(path) is not None:
            return None
        return f"{path}: exists and is not an output of ultraboneudf (no sidecar {side.name})"
    if "sha256" in meta and _sha256(path) != meta["sha256"]:
        return f"{path}: changed since ultraboneudf wrote it (its SHA-256 differs from {side.name})"
    return None


def _folder_files(folder: Path) -> Iterable[Path]:
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            yield Path(root) / name
        for name in dirs:  # a link to a folder is listed as a folder: it is not ours either
            if os.path.islink(os.path.join(root, name)):
                yield Path(root) / name


def folder_hashes(folder: str | os.PathLike) -> dict[str, str]:
    """``{relative path: SHA-256}`` of every file under ``folder`` but its record."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): _sha256(p) for p in _folder_files(folder)
            if p.relative_to(folder).as_posix() != FOLDER_RECORD}


def _folder_problem(path: Path, resumable: bool) -> str | None:
    """Why the folder output ``path`` may not be replaced (or, ``resumable``, added to)."""
    if not os.path.lexists(path):
        return None
    files = list(_folder_files(path))
    if not files:
        return None
    meta = read_record(path / FOLDER_RECORD)
    if meta is None:
        first = next(f for f in files)
        return (f"{path}: the folder holds files ultraboneudf did not write (e.g. "
                f"{first.relative_to(path)}); choose a new folder")
    if resumable:
        return None
    listed = meta.get("files", {})
    for f in files:
        rel = f.relative_to(path).as_posix()
        if rel == FOLDER_RECORD:
            continue
        if rel not in listed or f.is_symlink() or not f.is_file():
            return f"{f}: in {path} but not written by ultraboneudf; choose a new folder"
        if _sha256(f) != listed[rel]:
            return f"{f}: changed since ultraboneudf wrote it; choose a new folder"
    return None


# ------------------------------------------------------------------------------------------------
# the checks before any work


def _nearest_existing(path: Path) -> Path:
    for p in (path, *path.parents):
        if os.path.lexists(p):
            return p
    return Path(".")


def check_name(path: Path, also: Iterable[Path] = ()) -> Path:
    """The nearest existing folder above ``path`` when the file system can hold ``path`` (and the
    names in ``also``: a sidecar); else :class:`InputError` naming the name that is too long."""
    folder = _nearest_existing(path.parent if path.parent != path else path)
    if not folder.is_dir():
        raise InputError(f"{path}: cannot write into {folder} (not a folder)")
    try:
        name_max = os.pathconf(folder, "PC_NAME_MAX")
        path_max = os.pathconf(folder, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):
        name_max, path_max = 255, 4096
    for p in (path, *also):
        size = len(os.fsencode(p.name))
        if size > name_max:
            what = "the name" if p == path else f"the name of its sidecar {p.name[:20]}…{p.name[-10:]}"
            raise InputError(f"{path}: {what} is {size} bytes long, more than the {name_max} this file "
                             f"system holds; choose a shorter name")
        if len(os.fsencode(os.path.abspath(p))) >= path_max:
            raise InputError(f"{p}: the path is longer than the {path_max} bytes this file system holds")
    return folder


def _not_an_input(path: Path, targets: list[Path], inputs: Iterable[str | os.PathLike], folder: bool) -> None:
    for given in map(Path, inputs):
        if not os.path.lexists(given):
            continue
        real = given.resolve()
        for out in targets:
            where = Path(os.path.abspath(out)).resolve()
            if given.is_dir() and where.is_relative_to(real):
                raise InputError(f"{out}: inside the input folder {given}; write the output elsewhere")
            if os.path.lexists(out) and os.path.exists(out) and out.samefile(given):
                raise InputError(f"{out}: is the input; the input is never overwritten, choose another "
                                 f"output name")
        if folder and real.is_relative_to(Path(os.path.abspath(path)).resolve()):
            raise InputError(f"{path}: holds the input {given}; the input is never overwritten, choose "
                             f"another folder")


def check_output(path: str | os.PathLike, *, inputs: Iterable[str | os.PathLike] = (),
                 overwrite: bool = False, kind: str = "file", free_bytes: int = FREE_SPACE_BYTES) -> Path:
    """Check, before any work, that an output can be written and loses nothing; returns ``path``.

    ``kind``: ``file`` (with its sidecar ``X.json``), ``folder`` (replaced as a whole), ``run`` (a
    folder written into over several runs: new, empty or one of ours) or ``bare`` (a file without
    a record, whose owner the caller checks: only its name, place and folder are checked here). Refused with :class:`InputError` naming the file: a name the file system cannot
    hold; an output that is an input, inside an input folder, or (a folder) holds an input; a
    folder where a file goes, a file where a folder goes, a special file, the current folder;
    something this package did not write, or changed since (unless ``overwrite``); a folder that
    cannot be written into or has less than ``free_bytes`` free."""
    path = Path(path)
    folder_kind = kind in ("folder", "run")
    side = [sidecar_path(path)] if kind == "file" else []
    existing = check_name(path, side)
    if path.parent.is_dir():
        recover(path.parent)
    special = _special(path)
    if special is not None:
        raise InputError(f"{path}: is {special}, not an output file; choose another name")
    if folder_kind:
        if os.path.lexists(path) and (path.is_symlink() or not path.is_dir()):
            raise InputError(f"{path}: exists and is not a folder; choose another name")
        real = Path(os.path.abspath(path)).resolve()
        if kind == "folder" and (Path.cwd().resolve().is_relative_to(real) or os.path.ismount(real)):
            raise InputError(f"{path}: is the current folder, holds it, or is a mount point; a folder "
                             f"output is replaced as a whole, name a new folder")
    _not_an_input(path, [path, *side], inputs, folder_kind)
    if not folder_kind and path.is_dir() and not path.is_symlink():
        raise InputError(f"{path}: is a folder; choose a file name")
    problem = None if kind == "bare" else verify_output(path, kind)
    if problem is not None and not overwrite:
        raise InputError(f"{problem} (or --overwrite)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{path}: cannot write into {existing} (permission denied)")
    free = shutil.disk_usage(existing).free
    if free < free_bytes:
        raise InputError(f"{path}: only {free / 2**20:.0f} MB free in {existing}; need at least "
                         f"{free_bytes >> 20} MB")
    return path


def verify_output(path: Path, kind: str = "file") -> str | None:
    """Why an existing ``path`` is not an output of ours that may be replaced, or ``None``."""
    if kind in ("folder", "run"):
        return _folder_problem(path, resumable=kind == "run")
    return _file_problem(path)


# ------------------------------------------------------------------------------------------------
# writing


def _json_bytes(obj: Any) -> bytes:
    return (json.dumps(obj, indent=2) + "\n").encode("utf-8")


def write_outputs(files: Iterable[tuple[str | os.PathLike, bytes, dict[str, Any]]] = (),
                  folders: Iterable[tuple[str | os.PathLike, Callable[[Path], Any], dict[str, Any]]] = (), *,
                  overwrite: bool = False, remove: Iterable[str | os.PathLike] = ()) -> list[Any]:
    """Write one result as a unit (:class:`~ultraboneudf.io.commit.Commit`): each file ``(path,
    data, meta)`` with its sidecar (``meta``, a :func:`record`, completed with the file's name and
    SHA-256); each folder ``(path, fill,
    meta)`` filled by ``fill(new folder)`` and given its record (``meta`` with every file's
    SHA-256), then put in place of ``path`` as a whole; the paths in ``remove`` removed. Just
    before, with the folders locked, every output is checked again: something not ours that
    appeared there during the run refuses the commit
    (:class:`~ultraboneudf.io.commit.WriteError`, nothing written). Returns what each ``fill``
    returned."""
    checks, results = [], []
    with Commit() as commit:
        for path, data, meta in files:
            path = Path(path)
            commit.write(path, data)
            commit.write(sidecar_path(path), _json_bytes({**meta, "output": path.name,
                                                          "sha256": sha256_bytes(data)}))
            checks.append((path, "file"))
        for path, fill, meta in folders:
            path = Path(path)
            staging = commit.folder(path)
            try:
                results.append(fill(staging))
                (staging / FOLDER_RECORD).write_bytes(_json_bytes({**meta, "files": folder_hashes(staging)}))
            except OSError as exc:
                if isinstance(exc, WriteError):
                    raise
                raise WriteError(exc.errno, f"{path}: cannot write ({exc.strerror or exc}); nothing "
                                            f"written, the earlier output kept") from None
            checks.append((path, "folder"))
        for gone in remove:
            commit.remove(gone)

        def verify() -> None:
            for path, kind in checks:
                problem = None if overwrite else verify_output(path, kind)
                if problem is not None:
                    raise WriteError(errno.EEXIST, f"{problem}; it changed during the run: nothing written")

        commit.commit(verify)
    return results


def write_output(path: str | os.PathLike, data: bytes, meta: dict[str, Any], *, overwrite: bool = False,
                 remove: Iterable[str | os.PathLike] = ()) -> Path:
    """Write the file ``path`` and its sidecar as a unit (:func:`write_outputs`); returns ``path``."""
    write_outputs([(path, data, meta)], overwrite=overwrite, remove=remove)
    return Path(path)


def write_folder_output(path: str | os.PathLike, fill: Callable[[Path], Any], meta: dict[str, Any], *,
                        overwrite: bool = False) -> Any:
    """Fill a new folder, add its record and put it in place of ``path`` as a unit
    (:func:`write_outputs`); returns what ``fill`` returned."""
    return write_outputs(folders=[(path, fill, meta)], overwrite=overwrite)[0]
