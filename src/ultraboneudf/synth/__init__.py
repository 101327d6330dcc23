"""Synthetic data with known truth: the demo phantom, open views of closed meshes, and the sweep
simulator (:mod:`.simulator`; its parameters in :mod:`.sweep_config`). The names below are
imported on first use (the command line's help needs the parameters, not trimesh)."""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {"Phantom": "phantom", "bone_phantom": "phantom", "facing_surface": "phantom",
          "sample_surface": "phantom"}

__all__ = list(_WHERE)


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        value = getattr(importlib.import_module(f".{_WHERE[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
