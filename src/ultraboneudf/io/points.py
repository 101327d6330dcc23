"""Point clouds in and out: readers by extension (:data:`POINT_READERS`), validation of the
coordinates (mm), and the writer of compounded sweep points. Every problem with a file is an
:class:`~ultraboneudf.errors.InputError` whose message names the file."""

from __future__ import annotations

import os
from io import BytesIO
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from ..errors import InputError

MIN_POINTS = 100


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


def load_sweep_columns(path: str | os.PathLike, n_points: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The probe positions ``(N, 3)`` (the file's unit) and frame indices ``(N,)`` that a point file
    written by ``sweep2points`` carries beside its points: PLY vertex properties ``probe_x``,
    ``probe_y``, ``probe_z`` and ``frame``; NPZ arrays ``probe_position`` and ``frame_index``. Each is
    ``None`` where the file has none, the frames also where it has no probe positions (other
    formats: both ``None``). ``n_points``: the rows :func:`load_points` read from the same file."""
    path = Path(path)
    suffix = path.suffix.lower()
    columns: dict[str, np.ndarray] = {}
    if suffix == ".ply":
        try:
            raw = trimesh.load(path, process=False).metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
        except Exception as exc:  # load_points has read it: only a file changed in between gets here
            raise InputError(f"{path}: cannot read PLY ({type(exc).__name__}: {exc})") from None
        names = () if raw is None or raw.dtype.names is None else raw.dtype.names
        if {"probe_x", "probe_y", "probe_z"} <= set(names):
            columns["probe"] = np.column_stack([raw[k].reshape(-1) for k in ("probe_x", "probe_y", "probe_z")])
        if "frame" in names:
            columns["frame"] = raw["frame"].reshape(-1)
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            for key, name in (("probe", "probe_position"), ("frame", "frame_index")):
                if name in data.files:
                    columns[key] = data[name]
    if "probe" not in columns:
        return None, None
    probe = np.asarray(columns["probe"], dtype=np.float64)
    if probe.shape != (n_points, 3):
        raise InputError(f"{path}: the probe positions must be one row of three per point ({n_points}), "
                         f"got shape {probe.shape}")
    return probe, columns.get("frame")


# --------------------------------------------------------------------------------------------
# the writer of compounded sweep points

POINT_SUFFIXES = (".ply", ".npz", ".npy", ".xyz", ".txt", ".csv")
"""The point cloud formats :func:`encode_points` writes."""


def encode_points(path: Path, cp: Any) -> bytes:
    """Bytes of a point file of compounded sweep points ``cp`` (:class:`~ultraboneudf.sweep.compound.
    CompoundedPoints`: points in mm, frame index, beam direction, probe position) in the format of
    ``path``'s suffix: ``.ply`` (binary, with every per-point field), ``.npz`` (every field),
    ``.npy`` (points), ``.csv`` / ``.xyz`` / ``.txt`` (points and frame index as text)."""
    suffix = path.suffix.lower()
    if suffix not in POINT_SUFFIXES:
        raise InputError(f"{path}: unknown point cloud extension {path.suffix!r}; use one of "
                         f"{', '.join(POINT_SUFFIXES)}")
    pts = cp.points
    if suffix == ".ply":
        n = len(pts)
        dtype = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("frame", "<i4"),
                          ("beam_x", "<f4"), ("beam_y", "<f4"), ("beam_z", "<f4"),
                          ("probe_x", "<f8"), ("probe_y", "<f8"), ("probe_z", "<f8")])
        rec = np.empty(n, dtype=dtype)
        rec["x"], rec["y"], rec["z"] = pts.T
        rec["frame"] = cp.frame_index
        rec["beam_x"], rec["beam_y"], rec["beam_z"] = cp.beam_direction.T
        rec["probe_x"], rec["probe_y"], rec["probe_z"] = cp.probe_position.T
        header = ["ply", "format binary_little_endian 1.0",
                  "comment bone points compounded from a tracked ultrasound sweep (ultraboneudf), mm",
                  "comment frame: source frame index; beam: unit beam direction; probe: scan-line origin",
                  f"element vertex {n}", "property double x", "property double y", "property double z",
                  "property int frame", "property float beam_x", "property float beam_y",
                  "property float beam_z", "property double probe_x", "property double probe_y",
                  "property double probe_z", "end_header"]
        return ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()
    if suffix == ".npz":
        buf = BytesIO()
        np.savez_compressed(buf, **cp.as_dict())
        return buf.getvalue()
    if suffix == ".npy":
        buf = BytesIO()
        np.save(buf, pts)
        return buf.getvalue()
    sep = "," if suffix == ".csv" else " "
    lines = ["x,y,z,frame"] if suffix == ".csv" else []
    lines += [f"{x:.6f}{sep}{y:.6f}{sep}{z:.6f}{sep}{f}" for (x, y, z), f in zip(pts, cp.frame_index)]
    return ("\n".join(lines) + "\n").encode("ascii")
