"""A compounded cloud's frames and beams, from the order of its points.

A cloud compounded from a tracked sweep and written frame by frame keeps each frame's points
together: a run of consecutive points lies exactly in one plane, the frame's image plane. Written as
a bone mask's pixels are listed, row by row from the probe down, the run also tells the frame's
beam: within an image row consecutive points step exactly along the probe's face (many steps share
that one direction), and from row to row the depth only grows. So each frame gives the line of its
beam and the side of its probe, the two things a compounded cloud otherwise lacks.

Nothing here assumes the order holds: a cloud in any other order yields no runs or no beams
(:func:`frames_from_order` finds no plane, :func:`beams_from_order` no shared step), and the caller
checks the beams it gets against the surface before it uses them
(:func:`~ultraboneudf.geometry.echo_layers.false_echoes`).
"""

from __future__ import annotations

import numpy as np

FRAME_PLANE_MM = 0.02   # consecutive points this close to one plane are one frame's
FRAME_MIN_POINTS = 5
_ROW_TOLERANCE_DEG = 0.5  # steps within an image row share their direction to this
_FLAT_MM = 1e-3           # a run whose depth never changes more than this is one row: no side
_MAX_STEP_BACK = 0.1      # the median frame of a cloud listed row by row steps back up less of its depth


def frames_from_order(points: np.ndarray, plane_mm: float = FRAME_PLANE_MM,
                      min_points: int = FRAME_MIN_POINTS) -> np.ndarray:
    """(N,) int: the frame of each of ``points`` (N, 3, mm, in the cloud's order): runs of at least
    ``min_points`` consecutive points within ``plane_mm`` of one plane, numbered in order; -1 for
    points in no such run."""
    p = np.asarray(points, dtype=np.float64)
    label = np.full(len(p), -1)
    if len(p) < 4:
        return label
    # where a run can begin: three points not on a line, and the point after them or the one
    # before in their plane (tested for all at once, so that a cloud in another order costs no loop
    # over its points)
    triples = np.stack([p[:-3], p[1:-2], p[2:-1]], axis=1)
    centres = triples.mean(axis=1)
    _, spreads, axes = np.linalg.svd(triples - centres[:, None, :])
    after = np.abs(np.einsum("ij,ij->i", p[3:] - centres, axes[:, 2])) < plane_mm
    before = np.zeros_like(after)
    before[1:] = np.abs(np.einsum("ij,ij->i", p[:-4] - centres[1:], axes[1:, 2])) < plane_mm
    begins = np.flatnonzero((spreads[:, 1] >= 1e-3) & (after | before))
    start, frame = 0, 0
    while (k := np.searchsorted(begins, start)) < len(begins):
        start = int(begins[k])
        end = start + 3
        centre, normal = centres[start], axes[start, 2]
        while end < len(p) and abs((p[end] - centre) @ normal) < plane_mm:
            end += 1
            if (end - start) & (end - start - 1) == 0:  # refit at powers of two: the plane of the run
                centre = p[start:end].mean(axis=0)
                normal = np.linalg.svd(p[start:end] - centre)[2][2]
        first = start
        while first > 0 and label[first - 1] < 0 and abs((p[first - 1] - centre) @ normal) < plane_mm:
            first -= 1  # the frame's first points, on one line (an image row), fixed no plane alone
        if end - first >= min_points:
            label[first:end] = frame
            frame, start = frame + 1, end
        else:
            start += 1
    return label


def beams_from_order(points: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(N, 3): each point's beam, the unit direction from the probe into the tissue, from its frame
    (``frames`` from :func:`frames_from_order`) listed row by row (module docstring); zero rows where
    the frame tells none: in no frame, no two steps along one row, or one row only (no depth); all
    zero where the median frame steps back up the beam more than a tenth of its depth steps (a
    cloud listed along its echoes' curve, not row by row)."""
    p = np.asarray(points, dtype=np.float64)
    beams = np.zeros_like(p)
    frames = np.asarray(frames)
    if len(p) == 0:
        return beams
    order = np.argsort(frames, kind="stable")
    cuts = np.flatnonzero(np.diff(frames[order])) + 1
    back = []
    for rows in np.split(order, cuts):
        if frames[rows[0]] >= 0 and len(rows) >= 3:
            beam, stepped_back = frame_beam(p[rows])
            if beam.any():
                beams[rows] = beam
                back.append(stepped_back)
    # listed row by row, a frame's depth only grows (but where two frames in one plane merged); a
    # cloud listed along its echoes' curve steps back up about as much as down, whatever its steps
    if back and np.median(back) > _MAX_STEP_BACK:
        beams[:] = 0.0
    return beams


def frame_beam(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The beam (3,) of one frame's ``points`` (M, 3, in their order; module docstring), or zeros,
    and the share of the frame's depth steps along it that step back up toward the probe."""
    centred = points - points.mean(axis=0)
    e1, e2, normal = np.linalg.svd(centred, full_matrices=False)[2]
    steps = np.diff(centred, axis=0)
    x, y = steps @ e1, steps @ e2
    moving = np.hypot(x, y) > 1e-9
    if moving.sum() < 2:
        return np.zeros(3), 0.0
    angle = np.sort(np.degrees(np.arctan2(y[moving], x[moving])) % 180.0)
    wrapped = np.concatenate([angle, angle + 180.0])
    # how many step directions lie within the tolerance above each: the row's direction is the most shared
    shared = np.searchsorted(wrapped, angle + _ROW_TOLERANCE_DEG, side="right") - np.arange(len(angle))
    first = int(np.argmax(shared))
    if shared[first] < 2:
        return np.zeros(3), 0.0
    row = np.radians(np.median(wrapped[first:first + shared[first]]))
    beam = np.cross(normal, np.cos(row) * e1 + np.sin(row) * e2)
    depth = steps @ beam
    down, up = np.maximum(depth, 0.0).sum(), np.maximum(-depth, 0.0).sum()
    if max(down, up) < _FLAT_MM:
        return np.zeros(3), 0.0
    return (beam, up / (down + up)) if down >= up else (-beam, down / (down + up))
