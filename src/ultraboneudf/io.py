"""Reading point clouds and meshes, writing meshes and JSON atomically, validating input.

Point clouds are in millimetres, as ``(N, 3)`` float64 arrays. Readers are chosen by extension
(:data:`POINT_READERS`); every problem with a file is an :class:`~ultraboneudf.errors.InputError`
whose message names the file. Writers never leave a half-written file: they write a temporary file
beside the target and rename it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from .errors import InputError

MIN_POINTS = 100
MESH_SUFFIXES = (".ply", ".obj", ".stl")


# --------------------------------------------------------------------------------------------
# validation

PLAUSIBLE_EXTENT_MM = (5.0, 5000.0)
"""A bone scan spans more than 5 mm and less than 5 m."""
MAX_COORDINATE_MM = 1e6


def validate_points(points: Any, source: str = "points", min_points: int = MIN_POINTS) -> np.ndarray:
    """Check an ``(N, ≥3)`` array of coordinates (mm) and return it as ``(N, 3)`` float64.

    Raises :class:`InputError` naming ``source`` for a wrong shape, NaN/Inf, fewer than
    ``min_points`` points, or a degenerate cloud (all points identical or on one line).
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: cannot be read as an array of numbers") from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise InputError(f"{source}: expected an N×3 array of coordinates, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr[:, :3])
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InputError(f"{source}: {int(bad.sum())} point(s) contain NaN or Inf "
                         f"(first at point {first})")
    _check_coordinates(arr, source)   # before any numerics: a coordinate of 1e30 overflows them
    if len(arr) < min_points:
        raise InputError(f"{source}: only {len(arr)} points; at least {min_points} are needed")
    centred = arr - arr.mean(axis=0)
    sv = np.linalg.svd(centred[:: max(1, len(arr) // 200_000)], compute_uv=False)
    if sv[0] <= 1e-12 * max(1.0, np.abs(arr).max()):
        raise InputError(f"{source}: all points are identical; a surface needs spread in two directions")
    if sv[1] <= 1e-6 * sv[0]:
        raise InputError(f"{source}: the points are collinear; a surface needs spread in two directions")
    return arr


def _check_coordinates(points: np.ndarray, source: str) -> None:
    """Raise :class:`InputError` when a coordinate of ``points`` (N, 3) is ±10⁶ mm or beyond."""
    far = np.abs(points).max(axis=1) >= MAX_COORDINATE_MM
    if far.any():
        raise InputError(f"{source}: {int(far.sum())} point(s) have a coordinate beyond ±10⁶ mm (1 km), "
                         f"e.g. point {int(np.flatnonzero(far)[0])}: {points[far][0].tolist()}; the points "
                         f"cannot be a bone scan in mm")


def check_units(points: np.ndarray, source: str = "points") -> None:
    """Raise :class:`InputError` when ``points`` (N, 3), meant to be millimetres, cannot be: a
    coordinate beyond 10⁶ mm, or an extent outside :data:`PLAUSIBLE_EXTENT_MM` — naming the unit
    the numbers look like and the option that converts them."""
    _check_coordinates(points, source)
    extent = float(np.ptp(points, axis=0).max())
    lo, hi = PLAUSIBLE_EXTENT_MM
    if extent < lo:
        unit = "m" if extent * 1000.0 >= lo else "a unit larger than metres"
        raise InputError(f"{source}: the points span only {extent:.3g} mm; that looks like {unit}, not "
                         f"mm (convert to mm, or pass --units m or --units cm)")
    if extent > hi:
        raise InputError(f"{source}: the points span {extent:.3g} mm (more than 5 m); that looks like "
                         f"micrometres, not mm (convert to mm, or pass --units um)")


# --------------------------------------------------------------------------------------------
# point readers


def _first_data_line(lines: list[str]) -> int:
    for i, line in enumerate(lines):
        s = line.strip()
        if s and not s.startswith(("#", "//")):
            return i
    return -1


def _parse_rows(path: Path, lines: list[str], start: int, delimiter: str | None) -> np.ndarray:
    """Parse numeric rows (first three columns) line by line; the error names the line number."""
    rows = []
    for i in range(start, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith(("#", "//")):
            continue
        parts = [p for p in (s.split(delimiter) if delimiter else s.split()) if p.strip() != ""]
        if len(parts) < 3:
            raise InputError(f"{path}: line {i + 1}: expected at least 3 numbers, got {len(parts)}: "
                             f"{s[:60]!r}")
        try:
            rows.append((float(parts[0]), float(parts[1]), float(parts[2])))
        except ValueError:
            raise InputError(f"{path}: line {i + 1}: cannot parse numbers from {s[:60]!r}") from None
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _read_text(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8", errors="strict").splitlines()
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None


def _read_xyz(path: Path) -> np.ndarray:
    lines = _read_text(path)
    start = _first_data_line(lines)
    if start < 0:
        raise InputError(f"{path}: contains no points")
    delimiter = "," if "," in lines[start] else None
    try:  # fast path in C; on any problem fall back to the line-by-line parser for a precise error
        arr = np.loadtxt(path, delimiter=delimiter, usecols=(0, 1, 2), comments=("#", "//"),
                         ndmin=2, dtype=np.float64)
        if arr.size:
            return arr
    except (ValueError, IndexError):
        pass
    return _parse_rows(path, lines, start, delimiter)


def _read_csv(path: Path) -> np.ndarray:
    lines = _read_text(path)
    start = _first_data_line(lines)
    if start < 0:
        raise InputError(f"{path}: contains no points")
    header = [h.strip().strip('"').lower() for h in lines[start].split(",")]
    try:
        [float(h) for h in header[:3]]
        has_header = False
    except ValueError:
        has_header = True
    if not has_header:
        return _parse_rows(path, lines, start, ",")
    cols = (0, 1, 2)
    if all(name in header for name in ("x", "y", "z")):
        cols = tuple(header.index(name) for name in ("x", "y", "z"))
    rows = []
    for i in range(start + 1, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split(",")
        try:
            rows.append(tuple(float(parts[c]) for c in cols))
        except (ValueError, IndexError):
            raise InputError(f"{path}: line {i + 1}: cannot parse numbers from {s[:60]!r}") from None
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


MAX_PLY_VERTICES = int(os.environ.get("ULTRABONEUDF_MAX_PLY_VERTICES", 500_000_000))
"""A PLY header declaring more vertices than this is refused before anything is allocated."""

_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
              "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
              "double": 8, "float64": 8}


def _ply_header(path: Path) -> tuple[str, int, int | None, int]:
    """``(format, declared vertices, bytes per vertex or None (a list property), header bytes)`` of
    a PLY file, read from its header alone."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no end_header in the first 64 KiB)")
    header_bytes = head.find(b"\n", end) + 1
    fmt, vertices, row, element = "", 0, 0, None
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            element = words[1]
            if element == "vertex":
                try:
                    vertices = int(words[2])
                except ValueError:
                    raise InputError(f"{path}: bad vertex count {words[2]!r} in the PLY header") from None
        elif words[:1] == ["property"] and element == "vertex" and row is not None:
            row = None if words[1:2] == ["list"] else row + _PLY_SIZES.get(words[1], 0)
    return fmt, vertices, row, header_bytes


def _read_ply(path: Path) -> np.ndarray:
    fmt, declared, row, header_bytes = _ply_header(path)
    if declared > MAX_PLY_VERTICES:
        raise InputError(f"{path}: the header declares {declared:,} vertices, more than the limit of "
                         f"{MAX_PLY_VERTICES:,} (ULTRABONEUDF_MAX_PLY_VERTICES)")
    if fmt.startswith("binary") and row and path.stat().st_size < header_bytes + declared * row:
        raise InputError(f"{path}: the header declares {declared:,} vertices ({declared * row:,} bytes) but "
                         f"the file holds {path.stat().st_size - header_bytes:,} bytes after its header "
                         f"(truncated?)")
    try:
        geom = trimesh.load(path, process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"{path}: cannot read PLY ({type(exc).__name__}: {exc})") from None
    vertices = getattr(geom, "vertices", None)
    if vertices is None:
        raise InputError(f"{path}: the PLY file holds no vertices")
    if len(vertices) != declared:
        raise InputError(f"{path}: the header declares {declared:,} vertices but the file holds "
                         f"{len(vertices):,} (truncated?)")
    return np.asarray(vertices, dtype=np.float64)


def _read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read NumPy file ({exc})") from None


def _read_npz(path: Path) -> np.ndarray:
    try:
        with np.load(path, allow_pickle=False) as data:
            if "points" not in data:
                raise InputError(f"{path}: no array named 'points' (found: {', '.join(data.files)})")
            return data["points"]
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read NumPy archive ({exc})") from None


POINT_READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".xyz": _read_xyz, ".txt": _read_xyz, ".pts": _read_xyz, ".csv": _read_csv,
    ".ply": _read_ply, ".npy": _read_npy, ".npz": _read_npz,
}


def load_points(path: str | os.PathLike, min_points: int = MIN_POINTS) -> np.ndarray:
    """Read a point cloud file (mm) into an ``(N, 3)`` float64 array, validated.

    Formats by extension: ``.xyz``/``.txt``/``.pts`` (whitespace or commas, ≥ 3 columns, extra
    columns ignored), ``.csv`` (optional header; columns ``x,y,z`` if named, else the first three),
    ``.ply`` (vertices), ``.npy`` (N×≥3), ``.npz`` (array ``points``).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a point cloud file")
    reader = POINT_READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(f"{path}: unknown point cloud extension {path.suffix!r}; "
                         f"supported: {', '.join(POINT_READERS)}")
    try:
        points = reader(path)
    except OSError as exc:  # permission denied, an I/O error: one line, not a traceback
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from None
    return validate_points(points, source=str(path), min_points=min_points)


# --------------------------------------------------------------------------------------------
# meshes


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


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _write_temp(path, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
    for given in map(Path, inputs):
        if not given.exists():
            continue
        for out in (mesh, side):
            if given.is_dir() and out.resolve().is_relative_to(given.resolve()):
                raise InputError(f"{out}: inside the input folder {given}; write the output elsewhere")
            if out.exists() and out.samefile(given):
                raise InputError(f"{out}: is the input; the input is never overwritten, choose another "
                                 f"output name")
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
    folder = mesh.parent if mesh.parent.exists() else next(
        (p for p in mesh.resolve().parents if p.exists()), Path("."))
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"{mesh}: cannot write into {folder} (permission denied)")
    free = shutil.disk_usage(folder).free
    if free < FREE_SPACE_BYTES:
        raise InputError(f"{mesh}: only {free / 2**20:.0f} MB free in {folder}; need at least "
                         f"{FREE_SPACE_BYTES >> 20} MB")
    return mesh


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
    with _sigterm_raises():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            for target, blob in blobs:
                temps.append(_write_temp(target, blob))
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


def _write_temp(target: Path, data: bytes) -> str:
    """``data`` in a new temporary file beside ``target`` with the permissions a plain ``open``
    would give; returns its name."""
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp


@contextlib.contextmanager
def _sigterm_raises():
    """While the block runs (main thread only), SIGTERM raises :class:`SystemExit` instead of
    killing the process, so that the block's clean-up runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise SystemExit(128 + signum)

    before = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def save_json(obj: Any, path: str | os.PathLike) -> None:
    """Write ``obj`` as indented JSON atomically."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2) + "\n").encode("utf-8"))


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (folders: of their sorted file names and contents)."""
    path = Path(path)
    h = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for f in files:
        if path.is_dir():
            h.update(str(f.relative_to(path)).encode())
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()
