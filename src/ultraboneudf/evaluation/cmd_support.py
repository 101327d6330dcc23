"""Small helpers shared by the ``evaluate`` and ``render`` commands."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import trimesh

from ..errors import InputError


def load_optional_mesh(path: str) -> Optional[trimesh.Trimesh]:
    """Read a mesh file; ``None`` when it is a valid mesh file holding no triangles (a method's
    counted failure). Missing, unreadable or non-mesh files raise :class:`InputError` naming it."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a mesh file")
    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"{p}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        return None
    return mesh
