"""Synthetic data with known truth: the demo phantom, open views of closed meshes, and the sweep
simulator (:mod:`.simulator`; its parameters in :mod:`.simulation_config`). The names below are
imported on first use (the command line's help needs the parameters, not trimesh)."""

from __future__ import annotations

from .._lazy import lazy_getattr

_WHERE = {"Phantom": "phantom", "bone_phantom": "phantom", "facing_surface": "phantom"}

__all__ = list(_WHERE)


__getattr__ = lazy_getattr(__name__, _WHERE, globals())
