"""Single files written whole or not at all: a file is staged beside its target and renamed
(:class:`~ultraboneudf.io.commit.Commit`), so a reader never sees it half-written and a signal
never leaves the staged file behind."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from .commit import Commit


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a staged file in the same folder and a rename."""
    with Commit() as commit:
        commit.write(path, data)
        commit.commit()


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
