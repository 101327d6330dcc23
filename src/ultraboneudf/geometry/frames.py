"""The image plane of each frame of a sweep, and its normal: the direction the probe moved in.

A tracked sweep images the bone in planar slices. A gap *between* slices (the frame spacing, or a
run of frames lost when the probe lifted or tracking dropped) is a place the probe did not look, so
the bone goes on across it; a gap *inside* a slice is a place it looked and found no echo. The
surface through the data (:mod:`~ultraboneudf.geometry.data_surface`) bridges the first kind further
than the second, and tells them apart by the gap's direction (along the image planes' normal) and
by the frames on either side (consecutive ones: a frame in between would have looked).
"""

from __future__ import annotations

import numpy as np

_MIN_SPAN = 0.05   # a frame's second principal extent must reach this × its first (not one line)
_MAX_THICK = 0.2   # and its third stay under this × its second (a plane, not a volume)


def frame_axes(points: np.ndarray, origins: np.ndarray, frame_index: np.ndarray) -> np.ndarray:
    """(N, 3) unit normal of the image plane of the frame that imaged each of ``points`` (N, 3): the
    least-squares plane through that frame's points and their scan-line origins ``origins`` (N, 3,
    same unit), ``frame_index`` (N,) naming the frame. Zero rows for a frame whose points and origins
    do not span a plane (a single point, all on one line, or not flat). Signs agree with the
    normal of the frame with the most points, so that averaging neighbouring points' axes (the
    voxel mean) does not cancel them; the axis is a direction, not an orientation."""
    points = np.asarray(points, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64)
    frames, inverse, counts = np.unique(np.asarray(frame_index), return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    normals = np.zeros((len(frames), 3))
    for f in range(len(frames)):  # once per frame, before training: a few hundred small SVDs
        rows = order[starts[f]:starts[f + 1]]
        if len(rows) < 2:  # with their origins, two points can still span a plane; one cannot
            continue
        both = np.concatenate([points[rows], origins[rows]])
        _, s, vt = np.linalg.svd(both - both.mean(axis=0), full_matrices=False)
        if s[1] >= _MIN_SPAN * s[0] and s[2] <= _MAX_THICK * s[1]:
            normals[f] = vt[2]
    ref = normals[int(np.argmax(np.where(np.any(normals != 0.0, axis=1), counts, -1)))]
    normals[normals @ ref < 0] *= -1.0
    return normals[inverse]


def sweep_ends(points: np.ndarray, frame_index: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(N, 3) for each of ``points`` (N, 3) in the sweep's first or last frame (by ``frame_index``),
    the unit direction out of the sweep across that frame's image plane: ``axes`` (N, 3, from
    :func:`frame_axes`) turned away from the next frame's (or the previous frame's) points; zero rows
    for the other frames, and for all when there is one frame or no axis. Past these planes the probe
    never looked."""
    points = np.asarray(points, dtype=np.float64)
    frames = np.asarray(frame_index).reshape(-1)
    out = np.zeros((len(points), 3))
    present = np.unique(frames)
    if len(present) < 2:
        return out
    for end, neighbour in ((present[0], present[1]), (present[-1], present[-2])):
        rows = frames == end
        axis = axes[rows].mean(axis=0)
        if not np.any(axis):
            continue
        toward = points[frames == neighbour].mean(axis=0) - points[rows].mean(axis=0)
        out[rows] = -np.sign(toward @ axis) * axis / np.linalg.norm(axis)
    return out
