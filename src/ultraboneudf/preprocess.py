"""Pre-processing in millimetres, and the one normalisation into unit space.

:func:`prepare` takes a cloud (mm) with the optional per-point attributes of a tracked sweep (the
probe position that imaged each point, its frame) through: validation, optional test noise, the
voxel mean (the attributes averaged with their points), the local-plane stage at
``data.surface_fit_mm`` or wider on a sparse cloud (outliers and false echo layers dropped, points
moved onto their planes, echoes in the shadow of others dropped) and the normalisation
(:class:`Normalizer`, fitted on the result). The result, a :class:`UnitCloud`, carries the
normaliser whose inverse maps the mesh back to mm (:mod:`ultraboneudf.pipeline`).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .config import Config, DataConfig
from .errors import InputError
from .geometry.echo_layers import false_echoes
from .geometry.frame_order import beams_from_order, frames_from_order
from .geometry.frames import frame_axes, sweep_ends
from .geometry.normalize import Normalizer
from .geometry.data_surface import DataSurface
from .geometry.surface_fit import LocalPlanes, fit_local_planes, radius_for_density, shadowed, steep_echoes
from .geometry.vectors import unit_rows
from .geometry.voxel import voxel_downsample, voxel_downsample_with
from .io import check_units, validate_points

# A steep face's few echoes are kept unless another point lies this far (to 10 mm) above them on
# their beam: a neighbouring scan line meets a face 80° from the beam up to about 3 mm higher
# within the shadow test's half millimetre of it (geometry.surface_fit.steep_echoes).
_STEEP_ECHO_SHADOW_MM = 3.0
# A cloud whose order tells the beams of fewer of its points than this was not written frame by frame.
_ORDER_MIN_SHARE = 0.1


@dataclass
class PointAttributes:
    """What rides along with each of N sweep points through the voxel mean (a voxel's attributes
    are the mean of its points'): the probe position (mm), and with the frames known, the image
    plane's normal, the frame's place in the sweep and the way out of the sweep at its first and
    last frames (:func:`~ultraboneudf.geometry.frames.sweep_ends`)."""

    probe: np.ndarray                       # (N, 3) mm
    frame_axis: np.ndarray | None = None    # (N, 3) unit normal of the point's image plane
    frame_order: np.ndarray | None = None   # (N,) the frame's rank among the sweep's frames
    frame_end: np.ndarray | None = None     # (N, 3) out of the sweep in its first/last frame, else 0

    @classmethod
    def of_sweep(cls, points: np.ndarray, probe: np.ndarray, frames: np.ndarray | None) -> "PointAttributes":
        """The attributes of ``points`` (N, 3) mm imaged from ``probe`` (N, 3) mm in ``frames`` (N,)
        (``None``: the probe positions only)."""
        if frames is None:
            return cls(probe)
        axes = frame_axes(points, probe, frames)
        order = np.unique(frames, return_inverse=True)[1].astype(np.float64)
        return cls(probe, axes, order, sweep_ends(points, frames, axes))

    @property
    def with_frames(self) -> bool:
        return self.frame_axis is not None

    def columns(self) -> np.ndarray:
        """(N, 3) or (N, 10) float64: the attributes side by side, for the voxel mean."""
        if not self.with_frames:
            return self.probe
        return np.concatenate([self.probe, self.frame_axis, self.frame_order.reshape(-1, 1), self.frame_end],
                              axis=1)

    @classmethod
    def from_columns(cls, columns: np.ndarray) -> "PointAttributes":
        """Inverse of :meth:`columns`."""
        if columns.shape[1] == 3:
            return cls(columns)
        return cls(columns[:, :3], columns[:, 3:6], columns[:, 6], columns[:, 7:10])

    def subset(self, keep: np.ndarray) -> "PointAttributes":
        """The attributes of the points ``keep`` (boolean mask or indices) selects."""
        return PointAttributes(*(None if a is None else a[keep] for a in dataclasses.astuple(self)))

    def settled(self) -> "PointAttributes":
        """After a voxel mean: the averaged unit vectors made unit again (zero stays zero), the frame
        rank an integer, the way out of the sweep kept only where most of a voxel's points had it
        (a voxel shared by two frames, rare at 0.1 mm, takes one of them)."""
        if not self.with_frames:
            return self
        axis = unit_rows(self.frame_axis)
        length = np.linalg.norm(self.frame_end, axis=1, keepdims=True)
        end = np.where(length > 0.5, self.frame_end / np.maximum(length, 1e-12), 0.0)
        return PointAttributes(self.probe, axis, np.rint(self.frame_order), end)


@dataclass
class UnitCloud:
    """A cloud after the pre-processing, in unit space, with its map back to mm."""

    points: np.ndarray          # (M, 3) unit space
    probe: np.ndarray | None    # (M, 3) unit space probe positions, if any
    planes: LocalPlanes | None  # the local planes of the points, lengths in unit space, if fitted
    normalizer: Normalizer
    input_points: int
    outliers: int               # points the local-plane stage dropped
    frames: int                 # distinct sweep frames given with the points (0: none given)
    order_frames: int           # frames whose beam the cloud's order told (0: none, or not asked)
    beams: np.ndarray | None    # (M, 3) each point's beam direction, from its probe or the cloud's order
                                # (zero rows: not told); None where neither tells
    voxel_mm: float             # the voxel edge used (data.voxel_size_mm, or coarser: data.max_voxels)
    plane_radius_mm: float      # the local planes' first radius (data.surface_fit_mm, or wider where sparse)
    voxel_s: float
    surface_fit_s: float

    def support(self, d: DataConfig) -> np.ndarray | DataSurface:
        """What the support trim measures distances to, in unit space: the points, or with local
        planes the surface through them, bridged across their gaps with ``data.bridge`` > 0 and
        across a sweep's frames with ``data.frame_bridge`` (its distance is the distance to the
        nearest point without; its normals serve ``extract.trim_normal_mm``)."""
        if self.planes is None:
            return self.points
        return DataSurface.from_planes(self.points, self.planes, d.bridge, frame_bridge=d.frame_bridge)


def prepare(points_mm: Any, cfg: Config, seed: int, source: str = "points", probe_positions: Any = None,
            frame_index: Any = None) -> tuple[np.ndarray, UnitCloud]:
    """The cloud ``points_mm`` (N, 3) checked (:class:`InputError` naming ``source``) and
    pre-processed as ``cfg.data`` says, with the optional per-point probe positions (N, 3) mm and
    frame indices (N,). Returns the checked points (mm) and the :class:`UnitCloud`."""
    points = validate_points(points_mm, source=source)
    check_units(points, source)
    probe = validate_probe(probe_positions, len(points), source)
    frames = validate_frames(frame_index, probe, source)
    return points, to_unit(points, probe, cfg, seed, source, frames)


def to_unit(points: np.ndarray, probe: np.ndarray | None, cfg: Config, seed: int,
            source: str = "points", frames: np.ndarray | None = None) -> UnitCloud:
    """The beams a cloud without probe positions tells by its order (``data.beams_from_order``),
    optional test noise, voxel mean (the :class:`PointAttributes` and beams follow their points), the
    local-plane stage in mm (outliers dropped, points moved onto their planes, normals kept), and
    the one normalisation into unit space."""
    t0 = time.perf_counter()
    d = cfg.data
    n_input = len(points)
    beams, order_frames = None, 0
    if probe is None and d.beams_from_order and d.front_echo_mm > 0 and d.surface_fit_mm > 0:
        order = frames_from_order(points)
        beams = beams_from_order(points, order)
        told = np.any(beams != 0, axis=1)
        # a few runs by chance in a cloud that was not written frame by frame tell nothing
        order_frames = len(np.unique(order[told])) if told.mean() >= _ORDER_MIN_SHARE else 0
        beams = beams if order_frames else None
    if d.noise_sigma_mm > 0:
        points = points + np.random.default_rng(seed + 1).normal(0.0, d.noise_sigma_mm, points.shape)
    attrs = None
    if probe is not None:
        attrs = PointAttributes.of_sweep(points, probe, frames if frames is not None and d.frame_bridge > 0 else None)
    voxel = d.voxel_size_mm
    voxelised, voxel_attrs, voxel_beams = _voxel_mean(points, attrs, beams, voxel)
    while d.max_voxels and len(voxelised) > d.max_voxels and voxel > 0:
        # a surface's voxel count falls with the square of the edge; 1.2× at least, so it converges
        voxel *= max(1.2, float(np.sqrt(len(voxelised) / d.max_voxels)))
        voxelised, voxel_attrs, voxel_beams = _voxel_mean(points, attrs, beams, voxel)
    t1 = time.perf_counter()
    planes, outliers, radius = None, 0, 0.0
    if d.surface_fit_mm > 0:
        radius = radius_for_density(voxelised, d.surface_fit_mm, d.surface_fit_points)
        voxelised, voxel_attrs, planes, outliers, voxel_beams = local_plane_stage(voxelised, voxel_attrs, d, source,
                                                                                  radius, voxel_beams)
        if voxel_attrs is not None and voxel_attrs.with_frames:
            a = voxel_attrs.settled()
            planes = dataclasses.replace(planes, frame_axis=a.frame_axis, frame_order=a.frame_order,
                                         frame_end=a.frame_end)
    elif d.denoise or d.outlier_sigmas > 0 or d.shadow_mm > 0 or d.front_echo_mm > 0 or d.min_component > 0:
        raise InputError("data.denoise, data.outlier_sigmas, data.shadow_mm, data.front_echo_mm and "
                         "data.min_component need the local planes: set data.surface_fit_mm > 0")
    if voxel_attrs is not None:
        voxel_beams = voxelised - voxel_attrs.probe
    normalizer = Normalizer.fit(voxelised)
    return UnitCloud(points=normalizer.forward(voxelised),
                     probe=None if voxel_attrs is None else normalizer.forward(voxel_attrs.probe),
                     planes=None if planes is None else planes.scaled(1.0 / normalizer.scale),
                     normalizer=normalizer, input_points=n_input, outliers=outliers,
                     frames=0 if frames is None else len(np.unique(frames)), order_frames=order_frames,
                     beams=None if voxel_beams is None else unit_rows(voxel_beams),
                     voxel_mm=voxel,
                     plane_radius_mm=radius,
                     voxel_s=t1 - t0, surface_fit_s=time.perf_counter() - t1)


def _voxel_mean(points: np.ndarray, attrs: PointAttributes | None, beams: np.ndarray | None, voxel: float
                ) -> tuple[np.ndarray, PointAttributes | None, np.ndarray | None]:
    """Voxel mean of the points (mm); each voxel's attributes (and beams) are the mean of its points'."""
    if attrs is not None:
        voxelised, columns = voxel_downsample_with(points, attrs.columns(), voxel)
        return voxelised, PointAttributes.from_columns(columns), None
    if beams is not None:
        voxelised, beams = voxel_downsample_with(points, beams, voxel)
        return voxelised, None, beams
    return voxel_downsample(points, voxel), None, None


def local_plane_stage(points: np.ndarray, attrs: PointAttributes | None, d: DataConfig, source: str,
                      radius: float, beams: np.ndarray | None = None
                      ) -> tuple[np.ndarray, PointAttributes | None, LocalPlanes, int, np.ndarray | None]:
    """Robust local planes of the voxelised ``points`` (N, 3) mm at ``radius`` mm
    (``data.surface_fit_mm``, or the wider one :func:`radius_for_density` gives a sparse cloud),
    ``data.denoise`` times (at least once): drop the false echo layers (``front_echo_mm``,
    ``min_component``) and the outliers (``outlier_sigmas``), move the points onto their planes
    (``denoise``), drop the echoes in the shadow of others along their beam (``shadow_mm``; needs
    the probe positions). ``beams`` (N, 3): those a cloud without probe positions tells by its
    order (:mod:`~ultraboneudf.geometry.frame_order`), for the false echoes' side. Returns the
    points, their attributes, their last planes, the number dropped and the kept points' beams."""
    planes, dropped = None, 0
    for _ in range(max(1, d.denoise)):
        view = None
        if attrs is not None:  # sweep points: the planes must face the probe
            view = unit_rows(points - attrs.probe)
        planes = fit_local_planes(points, radius, view=view, steep_deg=d.steep_planes_deg)
        keep = ~false_echoes(points, planes, view, depth=d.front_echo_mm, ratio=d.front_echo_ratio,
                             fraction=d.min_component, beams=beams)
        if d.outlier_sigmas > 0:
            spare = None if view is None else steep_echoes(points, view, planes, _STEEP_ECHO_SHADOW_MM)
            keep &= ~planes.outliers(d.outlier_sigmas, 0.1 * radius, spare)
        if not keep.any():
            raise InputError(f"{source}: no point has enough neighbours within {radius:g} mm "
                             f"(data.surface_fit_mm) to form a surface (is the cloud in mm?)")
        if d.denoise:
            points = planes.projected(points)
        if view is not None and d.shadow_mm > 0:  # among the points kept so far
            rows = np.flatnonzero(keep)
            keep[rows[shadowed(points[rows], view[rows], d.shadow_mm)]] = False
        dropped += int((~keep).sum())
        points, planes = points[keep], planes.subset(keep)
        attrs = None if attrs is None else attrs.subset(keep)
        beams = None if beams is None else beams[keep]
    return points, attrs, planes, dropped, beams


def validate_frames(frame_index: Any, probe: np.ndarray | None, source: str) -> np.ndarray | None:
    """``frame_index`` as an (N,) int64 array matching the N probe positions, or ``None``."""
    if frame_index is None:
        return None
    if probe is None:
        raise InputError(f"{source}: frame indices need the probe positions of the points too")
    try:
        frames = np.asarray(frame_index)
    except (TypeError, ValueError):
        frames = np.asarray([])
    if frames.shape != (len(probe),) or not np.issubdtype(frames.dtype, np.integer):
        raise InputError(f"{source}: frame indices must be N integers, one per point (N = {len(probe)}), "
                         f"got shape {frames.shape} of {frames.dtype}")
    return frames.astype(np.int64)


def validate_probe(probe_positions: Any, n_points: int, source: str) -> np.ndarray | None:
    """``probe_positions`` as an (N, 3) float64 array matching the N points, or ``None``."""
    if probe_positions is None:
        return None
    try:
        probe = np.asarray(probe_positions, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: probe positions cannot be read as an array of numbers") from None
    if probe.shape != (n_points, 3):
        raise InputError(f"{source}: probe positions must be an N×3 array with one row per point "
                         f"(N = {n_points}), got shape {probe.shape}")
    if not np.isfinite(probe).all():
        raise InputError(f"{source}: probe positions contain NaN or Inf")
    return probe
