"""Geometry on point sets: down-sampling, FPS, nearest neighbours, query sampling, normals,
normalisation. Names are imported on first use, so that the evaluation can use the nearest
neighbours without loading PyTorch."""

from .._lazy import lazy_getattr

_WHERE = {"farthest_point_sampling": "fps", "NearestIndex": "neighbors", "knn_distance": "neighbors",
          "Normalizer": "normalize", "voxel_downsample": "voxel", "voxel_downsample_with": "voxel"}
__getattr__ = lazy_getattr(__name__, _WHERE, globals())
__all__ = sorted(_WHERE)
