"""Geometry on point sets: down-sampling, FPS, nearest neighbours, query sampling, normals,
normalisation."""

from .fps import farthest_point_sampling
from .neighbors import NearestIndex, knn_distance
from .normalize import Normalizer
from .voxel import voxel_downsample, voxel_downsample_with

__all__ = ["farthest_point_sampling", "NearestIndex", "knn_distance", "Normalizer", "voxel_downsample",
           "voxel_downsample_with"]
