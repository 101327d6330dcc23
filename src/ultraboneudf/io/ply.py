"""PLY headers read alone, to refuse a file before it is loaded: the elements it declares, and
whether the file holds as much as the header promises."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError

MAX_PLY_VERTICES = int(os.environ.get("ULTRABONEUDF_MAX_PLY_VERTICES", 500_000_000))
"""A PLY header declaring more vertices than this is refused before anything is allocated."""

_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
          "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
          "double": 8, "float64": 8}


@dataclass
class PlyHeader:
    """``format`` (``ascii``, ``binary_little_endian``…), the elements ``[(name, count, bytes per
    row or None when a list property makes rows vary)]`` in file order, and the header's length."""

    format: str
    elements: list[tuple[str, int, int | None]]
    header_bytes: int

    def count(self, name: str) -> int:
        return next((n for e, n, _ in self.elements if e == name), 0)


def read_ply_header(path: Path) -> PlyHeader:
    """The header of the PLY file ``path``; :class:`InputError` naming it when it is not a PLY file
    or declares more than :data:`MAX_PLY_VERTICES` vertices."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no end_header in the first 64 KiB)")
    fmt, elements = "", []
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            try:
                count = int(words[2])
            except ValueError:
                raise InputError(f"{path}: bad {words[1]} count {words[2]!r} in the PLY header") from None
            if count < 0:
                raise InputError(f"{path}: negative {words[1]} count {count} in the PLY header")
            elements.append([words[1], count, 0])
        elif words[:1] == ["property"] and elements and elements[-1][2] is not None:
            elements[-1][2] = None if words[1:2] == ["list"] else elements[-1][2] + _SIZES.get(words[1], 0)
    header = PlyHeader(fmt, [tuple(e) for e in elements], head.find(b"\n", end) + 1)
    vertices = header.count("vertex")
    if vertices > MAX_PLY_VERTICES:
        raise InputError(f"{path}: the header declares {vertices:,} vertices, more than the limit of "
                         f"{MAX_PLY_VERTICES:,} (ULTRABONEUDF_MAX_PLY_VERTICES)")
    return header


def check_ply_length(path: Path, header: PlyHeader) -> None:
    """:class:`InputError` naming ``path`` when it holds less than its header declares: fewer
    data lines (ASCII), or fewer bytes than fixed-size rows need (binary)."""
    size = path.stat().st_size - header.header_bytes
    if header.format == "ascii":
        declared = sum(n for _, n, _ in header.elements)
        lines = 0  # one element row per line
        with open(path, "rb") as fh:
            fh.seek(header.header_bytes)
            for block in iter(lambda: fh.read(1 << 22), b""):
                lines += block.count(b"\n")
            if size > 0:
                fh.seek(-1, os.SEEK_END)
                lines += fh.read(1) != b"\n"  # a last line without its newline
        if lines < declared:
            for name, n, _ in header.elements:  # the first element the lines run out in
                if lines < n:
                    what = {"vertex": "vertices", "face": "faces"}.get(name, f"'{name}' rows")
                    raise InputError(f"{path}: the header declares {n:,} {what} but the file holds "
                                     f"{lines:,} (truncated?)")
                lines -= n
        return
    fixed = 0
    for _, n, row in header.elements:
        if row is None:
            break  # rows of a list property vary: the loader checks the rest
        fixed += n * row
    if size < fixed:
        vertices = header.count("vertex")
        raise InputError(f"{path}: the header declares {vertices:,} vertices ({fixed:,} bytes) but the file "
                         f"holds {size:,} bytes after its header (truncated?)")
