"""Synthetic data with known truth: the demo phantom, open views of closed meshes, and the sweep
simulator."""

from .phantom import Phantom, bone_phantom, facing_surface, sample_surface

__all__ = ["Phantom", "bone_phantom", "facing_surface", "sample_surface"]
