"""Point clouds in and out: readers by extension (:data:`POINT_READERS`), validation of the
coordinates (mm), and the writer of compounded sweep points. Every problem with a file is an
:class:`~ultraboneudf.errors.InputError` whose message names the file."""

from __future__ import annotations

import os
from io import BytesIO
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError
from .inputs import check_fits_memory, check_input
from .ply import check_ply_length, read_ply_header

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
    if arr.shape[0] < min_points <= arr.shape[1] and arr.shape[0] <= 4:
        raise InputError(f"{source}: got shape {arr.shape}, one point per column; points go one per "
                         f"row (N×3): transpose the array")
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
# point readers: each checks, before it allocates, that the points fit in memory

MAX_TEXT_PROBE = 1 << 20
"""Bytes read from the start of a text cloud to find its first data line and its line length."""
_COPIES = 3
"""Arrays of the cloud's size alive at once while it is read and validated (parsed, float64, check)."""


def _is_data(line: str) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith(("#", "//"))


def _text_start(path: Path) -> tuple[int, str, int]:
    """``(line number of the first data line (0-based), that line, estimated data lines)`` from the
    file's first :data:`MAX_TEXT_PROBE` bytes, before the whole is read."""
    with open(path, "rb") as fh:
        head = fh.read(MAX_TEXT_PROBE)
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:
        if exc.start < len(head) - 4:  # not a character cut at the end of the probe
            raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None
        text = head[:exc.start].decode("utf-8")
    lines = text.splitlines()
    if len(head) == MAX_TEXT_PROBE and lines:
        lines = lines[:-1]  # the last line of the probe may be cut
    start = next((i for i, line in enumerate(lines) if _is_data(line)), -1)
    if start < 0:
        if len(head) < MAX_TEXT_PROBE:
            raise InputError(f"{path}: contains no points")
        raise InputError(f"{path}: no point in its first {MAX_TEXT_PROBE >> 20} MiB; not a point cloud")
    data = [line for line in lines[start:] if _is_data(line)]
    per_line = max(1.0, sum(len(line) + 1 for line in data) / len(data))
    return start, lines[start], int(path.stat().st_size / per_line) + 1


def _check_rows(path: Path, rows: int, what: str) -> None:
    check_fits_memory(path, rows * 3 * 8 * _COPIES, f"its {rows:,} {what}")


def _text_lines(path: Path):
    """``(line number, stripped line)`` of every data line, read as the file is, not whole."""
    try:
        with open(path, encoding="utf-8", errors="strict") as fh:
            for i, line in enumerate(fh, start=1):
                s = line.strip()
                if s and not s.startswith(("#", "//")):
                    yield i, s
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None


def _separator(first: str, default: str | None) -> tuple[str | None, bool]:
    """``(column separator, decimal comma)`` of a text cloud from its first data line: ``;`` where
    it holds one (spreadsheets write it where the comma is the decimal mark, which a comma inside
    its fields then is), else ``,`` where it holds one, else ``default`` (``None``: whitespace)."""
    first = first.split("#")[0]  # a comment after the numbers says nothing of their format
    if ";" in first:
        return ";", "," in first
    return ("," if "," in first else default), False


def _second_data_line(path: Path) -> str:
    """The text cloud's second data line, stripped ("" where it has none)."""
    return next((s for n, (_, s) in enumerate(_text_lines(path)) if n == 1), "")


def _parse_rows(path: Path, delimiter: str | None, columns: tuple[int, int, int] = (0, 1, 2),
                skip: int = 0, decimal_comma: bool = False) -> np.ndarray:
    """Parse numeric rows line by line (after ``skip`` data lines); the error names the line."""
    rows = []
    for n, (i, s) in enumerate(_text_lines(path)):
        if n < skip:
            continue
        parts = [p.strip().strip('"') for p in (s.split(delimiter) if delimiter else s.split())]
        parts = [p for p in parts if p != ""]
        if len(parts) <= max(columns):
            raise InputError(f"{path}: line {i}: expected at least {max(columns) + 1} numbers, got "
                             f"{len(parts)}: {s[:60]!r}")
        try:
            rows.append(tuple(float(parts[c].replace(",", ".") if decimal_comma else parts[c])
                              for c in columns))
        except ValueError:
            raise InputError(f"{path}: line {i}: cannot parse numbers from {s[:60]!r}") from None
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


def _loadtxt(path: Path, delimiter: str | None, columns: tuple[int, int, int], skip: int) -> np.ndarray | None:
    """NumPy's C parser over the file (it reads in blocks); ``None`` on any problem, for the line
    parser to name the line."""
    try:
        arr = np.loadtxt(path, delimiter=delimiter, usecols=columns, comments=("#", "//"), ndmin=2,
                         dtype=np.float64, skiprows=skip, encoding="utf-8", quotechar='"')
    except (ValueError, IndexError):
        return None
    return arr if arr.size else None


def _read_xyz(path: Path) -> np.ndarray:
    start, first, rows = _text_start(path)
    _check_rows(path, rows, "lines of text")
    # a PTS file (and some other exports) opens with its number of points
    count = first.strip().isdigit()
    if count:
        first = _second_data_line(path)
    delimiter, decimal_comma = _separator(first, None)
    arr = None if decimal_comma else _loadtxt(path, delimiter, (0, 1, 2), start + 1 if count else 0)
    return arr if arr is not None else _parse_rows(path, delimiter, skip=int(count), decimal_comma=decimal_comma)


def _read_csv(path: Path) -> np.ndarray:
    start, first, rows = _text_start(path)
    _check_rows(path, rows, "lines of text")
    delimiter, decimal_comma = _separator(first, ",")
    header = [h.strip().strip('"').lower() for h in first.split(delimiter)]
    try:
        [float(h.replace(",", ".") if decimal_comma else h) for h in header[:3]]
        has_header = False
    except ValueError:
        has_header = True
    if not has_header:
        arr = None if decimal_comma else _loadtxt(path, delimiter, (0, 1, 2), 0)
        return arr if arr is not None else _parse_rows(path, delimiter, decimal_comma=decimal_comma)
    # a header holds no numbers: the first data line tells the decimal mark
    decimal_comma = delimiter == ";" and "," in _second_data_line(path)
    cols = (0, 1, 2)
    if all(name in header for name in ("x", "y", "z")):
        cols = tuple(header.index(name) for name in ("x", "y", "z"))
    arr = None if decimal_comma else _loadtxt(path, delimiter, cols, start + 1)
    return arr if arr is not None else _parse_rows(path, delimiter, cols, skip=1, decimal_comma=decimal_comma)


def _read_ply(path: Path) -> np.ndarray:
    header = read_ply_header(path)
    declared = header.count("vertex")
    _check_rows(path, declared, "vertices")
    check_ply_length(path, header)
    import trimesh

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


def _npy_rows(path: Path, fh) -> int:
    """Rows of the ``.npy`` array whose header ``fh`` is at, read from the header alone."""
    try:
        version = np.lib.format.read_magic(fh)
        shape, _, _ = (np.lib.format.read_array_header_1_0(fh) if version == (1, 0)
                       else np.lib.format.read_array_header_2_0(fh))
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read NumPy file ({exc})") from None
    return int(shape[0]) if shape else 0


def _read_npy(path: Path) -> np.ndarray:
    with open(path, "rb") as fh:
        _check_rows(path, _npy_rows(path, fh), "points")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}: cannot read NumPy file ({exc})") from None


def _read_npz(path: Path) -> np.ndarray:
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            names = [n[:-4] for n in archive.namelist() if n.endswith(".npy")]
            # an archive of one array (``np.savez(path, cloud)``) holds the points whatever its name
            name = "points" if "points" in names or len(names) != 1 else names[0]
            if name not in names:
                raise InputError(f"{path}: no array named 'points' (it holds {', '.join(names) or 'none'}); "
                                 f"save the points as points=…")
            with archive.open(f"{name}.npy") as fh:
                _check_rows(path, _npy_rows(path, fh), "points")
        with np.load(path, allow_pickle=False) as data:
            return data[name]
    except InputError:
        raise
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: cannot read NumPy archive ({exc})") from None


POINT_READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".xyz": _read_xyz, ".txt": _read_xyz, ".pts": _read_xyz, ".csv": _read_csv,
    ".ply": _read_ply, ".npy": _read_npy, ".npz": _read_npz,
}


def load_points(path: str | os.PathLike, min_points: int = MIN_POINTS) -> np.ndarray:
    """Read a point cloud file (mm) into an ``(N, 3)`` float64 array, validated.

    Formats by extension: ``.xyz``/``.txt``/``.pts`` (whitespace, commas or semicolons, ≥ 3
    columns, extra columns ignored; a first line holding only the number of points, as a PTS
    file's, skipped), ``.csv`` (commas or semicolons; optional header; columns ``x,y,z`` if
    named, else the first three); with semicolons a comma in a number is its decimal mark, as
    spreadsheets write it in many locales; ``.ply`` (vertices), ``.npy`` (N×≥3), ``.npz`` (array
    ``points``, or its only array). A file whose points would not fit in the memory available is
    refused before it is read (text is read as a stream).
    """
    path = Path(path)
    reader = POINT_READERS.get(path.suffix.lower())
    if reader is None and not path.is_dir():
        check_input(path, "file")
        raise InputError(f"{path}: unknown point cloud extension {path.suffix!r}; "
                         f"supported: {', '.join(POINT_READERS)}")
    check_input(path, "file")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a point cloud file")
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
        import trimesh

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
