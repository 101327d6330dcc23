"""``reconstruct``: points (mm) → pre-processing → method → extraction → mesh (mm).

This is the one place where the cloud is normalised (:class:`Normalizer` fitted on the voxelised
cloud) and the one place where the mesh is mapped back to millimetres. Optional per-point probe
positions (from a tracked sweep) follow the points through voxelisation and the same normalisation.
"""

from __future__ import annotations

import dataclasses
import hashlib
import random
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import trimesh

from ._version import __version__
from .checkpoints import Checkpoint
from .config import (DEFAULT_PRESET, CleanConfig, Config, DataConfig, ExtractConfig, GridConfig, apply_overrides,
                     preset as make_preset, validate)
from .devices import resolve_device
from .errors import FitWarning, InputError
from .evaluation.data_fit import data_fit
from .extraction import extract_mesh, mesh_quality, trim_to_support
from .fields.base import Field
from .geometry.echo_layers import false_echoes
from .geometry.frames import frame_axes, sweep_ends
from .geometry.normalize import Normalizer
from .geometry.data_surface import DataSurface
from .geometry.surface_fit import LocalPlanes, fit_local_planes, shadowed, steep_echoes
from .geometry.voxel import voxel_downsample, voxel_downsample_with
from .io import check_outputs, check_units, save_mesh_with_sidecar, validate_points
from .methods import Fitted, get_method
from .methods import ultraboneudf as ubu
from .progress import Progress

# A steep face's few echoes are kept unless another point lies this far (to 10 mm) above them on
# their beam: a neighbouring scan line meets a face 80° from the beam up to about 3 mm higher
# within the shadow test's half millimetre of it (geometry.surface_fit.steep_echoes).
_STEEP_ECHO_SHADOW_MM = 3.0


@dataclass
class Reconstruction:
    """The result of :func:`reconstruct`: the mesh in mm (input frame) and its full provenance.

    ``mesh`` is ``None`` when the method found no surface (a failure, never an empty mesh).
    """

    mesh: trimesh.Trimesh | None
    method: str
    preset: str
    config: Config
    timings: dict[str, float]
    counts: dict[str, int]
    quality: dict[str, float]
    data_fit: dict[str, float]
    """The mesh against its own input (:func:`~ultraboneudf.evaluation.data_fit.data_fit`,
    ``extract.fit_mm``); empty when off."""
    device: str
    seed: int
    normalizer: Normalizer
    history: dict[str, list[float]] = field(default_factory=dict)
    input: dict[str, Any] = field(default_factory=dict)
    method_info: dict[str, Any] = field(default_factory=dict)
    """Choices the method resolved at run time (e.g. ``poisson_orientation``: ``tangent``/``probe``)."""
    surface: "FittedSurface | None" = dataclasses.field(default=None, repr=False)
    """What :func:`fit` gave, which :meth:`extract` extracts again (``None`` for a record read back)."""
    version: str = __version__

    @property
    def field(self) -> Field | None:
        """The trained field in unit space (``None`` for methods that give a mesh directly);
        :meth:`extract` extracts it again with other settings without retraining."""
        return None if self.surface is None else self.surface.field

    @property
    def support(self) -> np.ndarray | DataSurface | None:
        """What the support trim (``extract.trim_mm``, ``extract.trim_normal_mm``) measures distances
        to, in unit space."""
        return None if self.surface is None else self.surface.support

    def extract(self, **settings: Any) -> trimesh.Trimesh | None:
        """The trained field extracted again, in mm, with ``settings`` replacing fields of the
        configuration's ``extract``, ``clean`` or ``grid`` section (e.g. ``mode="faithful",
        max_depth=9, trim_mm=0``); the support trim applies as in :func:`reconstruct`. ``None`` when
        no surface is found."""
        if self.field is None:
            raise RuntimeError(f"method {self.method!r} gives a mesh directly; there is no field to extract")
        return self.surface.extract(**settings)

    def sidecar(self) -> dict[str, Any]:
        """The JSON sidecar (DESIGN.md): everything needed to trace the mesh to its configuration."""
        return {
            "method": self.method,
            "preset": self.preset,
            "config": self.config.to_dict(),
            "timings": {k: round(v, 4) for k, v in self.timings.items()},
            "counts": self.counts,
            "mesh_quality": self.quality,
            "data_fit": self.data_fit,
            "device": self.device,
            "seed": self.seed,
            "version": self.version,
            "input": self.input,
            "method_info": self.method_info,
            "normalization": self.normalizer.to_dict(),
            "loss_history": self.history,
        }

    def fit_warnings(self, limit: float = 0.01, cli: bool = False) -> list[str]:
        """One sentence per ``data_fit`` figure above ``limit`` (a fraction): input the mesh does not
        reach, or mesh area far from every input point. Empty when the mesh fits its input. The
        advice is spelled for Python (``seed=``, ``extract__trim_mm=``) or, with ``cli``, for the
        command line (``--seed``, ``--set extract.trim_mm=``). :func:`reconstruct` also issues each
        as a :class:`~ultraboneudf.errors.FitWarning`."""
        fit, out = self.data_fit, []
        if not fit:
            return out

        def setting(key: str, value: str) -> str:
            return f"--set {key}={value}" if cli else f"{key.replace('.', '__')}={value}"

        t = fit["threshold_mm"]
        if fit["input_far_fraction"] > limit:
            advice = "another --seed or --preset" if cli else "another seed= or preset="
            out.append(f"{100 * fit['input_far_fraction']:.1f}% of the input points are more than {t:g} mm "
                       "from the mesh (the field did not fit there, the mesh stops short of the data's "
                       f"rim, or the points are outliers); try {advice}")
        if fit["mesh_far_area_fraction"] > limit:
            text = (f"{100 * fit['mesh_far_area_fraction']:.1f}% of the mesh area is {t:g} mm or more "
                    "from every input point: ")
            if self.config.extract.trim_mm <= 0:
                text += f"surface the data does not support; {setting('extract.trim_mm', f'{t:g}')} removes it"
            elif self.config.data.bridge > 0:
                text += (f"surface interpolated across gaps in the data (data.bridge; "
                         f"{setting('data.bridge', '0')} leaves the gaps open)")
            else:
                text += "surface the data does not support"
            out.append(text)
        return out

    def save(self, path: str | Path) -> Path:
        """Write the mesh (format by suffix) and its sidecar ``NAME.EXT.json`` as a pair
        (:func:`~ultraboneudf.io.save_mesh_with_sidecar`: both or neither). An existing file is
        replaced only if it is an earlier output of this package with its sidecar
        (:func:`~ultraboneudf.io.check_outputs`). Returns the sidecar path."""
        if self.mesh is None:
            raise RuntimeError("no mesh to save: the reconstruction failed")
        path = check_outputs(path, (self.input["path"],) if self.input.get("path") else ())
        return save_mesh_with_sidecar(self.mesh, path, self.sidecar())


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def reconstruct(points_mm: Any, preset: str = DEFAULT_PRESET, device: str | torch.device = "auto",
                seed: int = 42, method: str = "ultraboneudf", *, config: Config | None = None,
                assignments: list[str] | tuple[str, ...] = (), progress: Progress | None = None,
                quiet: bool = True, source: str = "points", probe_positions: Any = None,
                frame_index: Any = None, checkpoint: Checkpoint | None = None,
                **overrides: Any) -> Reconstruction:
    """Reconstruct a bone surface mesh from a point cloud in millimetres.

    Parameters
    ----------
    points_mm : (N, 3) array-like, millimetres in the input's frame.
    preset : ``robust`` (the default: ultrasound-like points), ``fast`` (clean, dense clouds),
        ``official`` (the reference code) or ``paper`` (the paper's text); see
        :data:`~ultraboneudf.config.PRESET_HELP`.
    device : ``auto``, ``cpu``, ``cuda`` or a torch device.
    seed : seeds every random draw; same input, config, seed and device give the same mesh.
    method : a name from :data:`ultraboneudf.methods.METHODS`; its ``configure`` sets the method's
        own defaults (network, loss, schedule, extractor) on the preset before the overrides.
    config : a full :class:`Config` to use instead of the preset (taken as is: no method defaults).
    assignments, overrides : ``"section.key=value"`` strings and keyword overrides of the preset
        (``iters=1000``, ``extract__max_depth=8``).
    progress / quiet : a :class:`Progress` to report to, or ``quiet=False`` for a default one.
    source : the name used in error messages (a file name).
    probe_positions : optional (N, 3) array-like, mm in the same frame as ``points_mm``: row ``i`` is
        the position of the probe that imaged point ``i`` (``CompoundedPoints.probe_position`` from
        :func:`ultraboneudf.sweep.sweep_to_points`). Voxel-averaged with the points and normalised
        with the same map. Used by methods that can (Poisson orients its normals toward the probe,
        ``poisson.orientation``); ignored by the others.
    frame_index : optional (N,) integers, with ``probe_positions``: the frame (image) that imaged
        each point (``CompoundedPoints.frame_index``). The surface through the data then bridges the
        gaps between consecutive frames further than those inside one, and does not reach past the
        sweep's first and last image planes (``data.frame_bridge``).
    checkpoint : save the training's state every ``checkpoint.every`` steps to ``checkpoint.path``
        and, with ``checkpoint.resume``, continue a killed run from it (same result as an
        uninterrupted run); for the methods that train with the shared loop (not FUNSR or Poisson).
    """
    progress = progress or Progress(quiet=quiet)
    surface = fit(points_mm, preset, device, seed, method, config=config, assignments=assignments,
                  progress=progress, source=source, probe_positions=probe_positions, frame_index=frame_index,
                  checkpoint=checkpoint, **overrides)
    rec = _finish(surface, progress)
    _warn_fit(rec, source)
    return rec


def fit(points_mm: Any, preset: str = DEFAULT_PRESET, device: str | torch.device = "auto",
        seed: int = 42, method: str = "ultraboneudf", *, config: Config | None = None,
        assignments: list[str] | tuple[str, ...] = (), progress: Progress | None = None,
        quiet: bool = True, source: str = "points", probe_positions: Any = None,
        frame_index: Any = None, checkpoint: Checkpoint | None = None, **overrides: Any) -> "FittedSurface":
    """The first half of :func:`reconstruct` (same arguments): pre-process, normalise and fit the
    method, without extracting a mesh. :meth:`FittedSurface.extract` then gives the surface in mm,
    as often as wanted and with any extraction settings."""
    started = time.perf_counter()
    progress = progress or Progress(quiet=quiet)
    cfg, entry = configure(preset, method, config, overrides, assignments)
    if checkpoint is not None and not entry.takes_checkpoint:
        raise InputError(f"method {method} cannot checkpoint its training (no --checkpoint-every/--resume)")
    dev = resolve_device(device)
    points = validate_points(points_mm, source=source)
    check_units(points, source)
    probe = _validate_probe(probe_positions, len(points), source)
    frames = _validate_frames(frame_index, probe, source)
    seed_everything(seed)
    unit = _to_unit(points, probe, cfg, seed, source, frames)
    extra = {"probe": unit.probe} if entry.takes_probe else {}
    if entry.takes_planes:
        extra["planes"] = unit.planes
    if checkpoint is not None:
        extra["checkpoint"] = checkpoint
    fitted = entry.fit(unit.points, cfg, dev, seed, progress, **extra)
    return FittedSurface(method=method, preset=preset if config is None else "custom", config=cfg, device=dev,
                         seed=seed, fitted=fitted, unit=unit,
                         support=_support(unit.points, unit.planes, cfg.data),
                         input=input_record(points, source), started=started)


def input_record(points: np.ndarray, source: str) -> dict[str, Any]:
    """The sidecar's ``input`` for points given as an array: their name, count and the SHA-256 of
    their float64 bytes (the command line adds the file's path and hash)."""
    arr = np.ascontiguousarray(points, dtype=np.float64)
    return {"source": source, "points": int(len(arr)), "points_sha256": hashlib.sha256(arr.tobytes()).hexdigest()}


def _warn_fit(rec: Reconstruction, source: str) -> None:
    for text in rec.fit_warnings():
        warnings.warn(f"{source}: {text}", FitWarning, stacklevel=3)


def reconstruct_many(clouds_mm: Sequence[Any], preset: str = DEFAULT_PRESET, device: str | torch.device = "auto",
                     seed: int = 42, *, assignments: list[str] | tuple[str, ...] = (),
                     progress: Progress | None = None, quiet: bool = True,
                     sources: Sequence[str] | None = None, **overrides: Any) -> list[Reconstruction]:
    """Reconstruct several scans with UltraBoneUDF, training their fields together in one batched
    loop (:mod:`ultraboneudf.training`): for dataset runs, where per-step overhead dominates.

    Each scan is pre-processed, normalised, extracted and mapped back on its own, exactly as
    :func:`reconstruct` (same preset, overrides and ``seed`` for every scan), and its field equals the
    one :func:`reconstruct` trains, step for step. In each result ``timings.train_s`` and
    ``timings.total_s`` are those of the whole batch (shared); ``sources`` name the scans in errors.
    """
    t_start = time.perf_counter()
    progress = progress or Progress(quiet=quiet)
    clouds = list(clouds_mm)
    names = list(sources) if sources is not None else [f"scan {k}" for k in range(len(clouds))]
    if not clouds or len(names) != len(clouds):
        raise InputError("reconstruct_many needs at least one cloud and one source name per cloud")
    cfg, _ = configure(preset, "ultraboneudf", None, overrides, assignments)
    dev = resolve_device(device)
    units, records = [], []
    for cloud, name in zip(clouds, names):
        seed_everything(seed)
        cloud = validate_points(cloud, source=name)
        check_units(cloud, name)
        units.append(_to_unit(cloud, None, cfg, seed, name))
        records.append(input_record(cloud, name))
    fitted = ubu.fit_many([u.points for u in units], cfg, dev, seed, progress, [u.planes for u in units])
    out = [_finish(FittedSurface(method="ultraboneudf", preset=preset, config=cfg, device=dev, seed=seed, fitted=f,
                                 unit=unit, support=_support(unit.points, unit.planes, cfg.data),
                                 input=record, started=t_start), progress)
           for f, unit, record in zip(fitted, units, records)]
    for rec, name in zip(out, names):
        rec.timings["total_s"] = time.perf_counter() - t_start   # the batch's wall time, shared
        _warn_fit(rec, name)
    return out


@dataclass
class _UnitCloud:
    """A cloud after voxelisation (and the local-plane stage), in unit space, with its map back to mm."""

    points: np.ndarray          # (M, 3) unit space
    probe: np.ndarray | None    # (M, 3) unit space probe positions, if any
    planes: LocalPlanes | None  # the local planes of the points, lengths in unit space, if fitted
    normalizer: Normalizer
    input_points: int
    outliers: int               # points the local-plane stage dropped
    frames: int                 # distinct sweep frames given with the points (0: none given)
    voxel_mm: float             # the voxel edge used (data.voxel_size_mm, or coarser: data.max_voxels)
    voxel_s: float
    surface_fit_s: float


def configure(preset: str, method: str, config: Config | None = None, overrides: dict[str, Any] | None = None,
              assignments: list[str] | tuple[str, ...] = ()) -> tuple[Config, Any]:
    """The run's configuration: ``config`` as given, else the preset with the method's defaults,
    then the overrides; and the method's registry entry."""
    entry = get_method(method)
    cfg = config if config is not None else make_preset(preset)
    if config is None:
        entry.configure(cfg)  # the method's own defaults, before the user's overrides
    apply_overrides(cfg, overrides, assignments)
    return validate(cfg, trains=entry.trains), entry


def _to_unit(points: np.ndarray, probe: np.ndarray | None, cfg: Config, seed: int,
             source: str = "points", frames: np.ndarray | None = None) -> _UnitCloud:
    """Optional test noise, voxel mean (probe positions and, with ``frames``, the image planes'
    normals follow their points), the local-plane stage in mm (outliers dropped, points moved onto
    their planes, normals kept), and the one normalisation into unit space."""
    t0 = time.perf_counter()
    d = cfg.data
    n_input = len(points)
    if d.noise_sigma_mm > 0:
        points = points + np.random.default_rng(seed + 1).normal(0.0, d.noise_sigma_mm, points.shape)
    # the probe position, the image plane's normal and the frame's place in the sweep ride along
    # with each point as attributes
    attrs = probe
    with_frames = probe is not None and frames is not None and d.frame_bridge > 0
    if with_frames:
        order = np.unique(frames, return_inverse=True)[1].reshape(-1, 1)
        axes = frame_axes(points, probe, frames)
        attrs = np.concatenate([probe, axes, order, sweep_ends(points, frames, axes)], axis=1)
    voxel = d.voxel_size_mm
    voxelised, voxel_attrs = _voxel_mean(points, attrs, voxel)
    while d.max_voxels and len(voxelised) > d.max_voxels and voxel > 0:
        # a surface's voxel count falls with the square of the edge; 1.2× at least, so it converges
        voxel *= max(1.2, float(np.sqrt(len(voxelised) / d.max_voxels)))
        voxelised, voxel_attrs = _voxel_mean(points, attrs, voxel)
    t1 = time.perf_counter()
    planes, outliers = None, 0
    if d.surface_fit_mm > 0:
        voxelised, voxel_attrs, planes, outliers = _local_plane_stage(voxelised, voxel_attrs, d, source)
        if with_frames:
            # averaged unit vectors, made unit again (zero stays zero); a voxel shared by two frames
            # (rare at 0.1 mm) takes one of them, and is an end frame's only if mostly of its points
            axis, end = voxel_attrs[:, 3:6], voxel_attrs[:, 7:10]
            axis = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
            length = np.linalg.norm(end, axis=1, keepdims=True)
            end = np.where(length > 0.5, end / np.maximum(length, 1e-12), 0.0)
            planes = dataclasses.replace(planes, frame_axis=axis, frame_order=np.rint(voxel_attrs[:, 6]),
                                         frame_end=end)
    elif d.denoise or d.outlier_sigmas > 0 or d.shadow_mm > 0 or d.front_echo_mm > 0 or d.min_component > 0:
        raise InputError("data.denoise, data.outlier_sigmas, data.shadow_mm, data.front_echo_mm and "
                         "data.min_component need the local planes: set data.surface_fit_mm > 0")
    normalizer = Normalizer.fit(voxelised)
    voxel_probe = None if voxel_attrs is None else voxel_attrs[:, :3]
    return _UnitCloud(points=normalizer.forward(voxelised),
                      probe=None if voxel_probe is None else normalizer.forward(voxel_probe),
                      planes=None if planes is None else planes.scaled(1.0 / normalizer.scale),
                      normalizer=normalizer, input_points=n_input, outliers=outliers,
                      frames=0 if frames is None else len(np.unique(frames)), voxel_mm=voxel,
                      voxel_s=t1 - t0, surface_fit_s=time.perf_counter() - t1)


def _voxel_mean(points: np.ndarray, attrs: np.ndarray | None, voxel: float
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """Voxel mean of the points (mm); each voxel's attributes (probe position, ...) are the mean
    of its points'."""
    if attrs is None:
        return voxel_downsample(points, voxel), None
    return voxel_downsample_with(points, attrs, voxel)


def _local_plane_stage(points: np.ndarray, attrs: np.ndarray | None, d: DataConfig, source: str
                       ) -> tuple[np.ndarray, np.ndarray | None, LocalPlanes, int]:
    """Robust local planes of the voxelised ``points`` (N, 3) mm, ``data.denoise`` times (at least
    once): drop the outliers (``outlier_sigmas``), move the points onto their planes (``denoise``),
    drop the echoes in the shadow of others along their beam (``shadow_mm``; needs the probe
    positions, ``attrs[:, :3]``). Returns the points, their attributes, their last planes and the
    number dropped."""
    planes, dropped = None, 0
    for _ in range(max(1, d.denoise)):
        view = None
        if attrs is not None:  # sweep points: the planes must face the probe
            view = points - attrs[:, :3]
            view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
        planes = fit_local_planes(points, d.surface_fit_mm, view=view, steep_deg=d.steep_planes_deg)
        keep = ~false_echoes(points, planes, view, depth=d.front_echo_mm, ratio=d.front_echo_ratio,
                             fraction=d.min_component)
        if d.outlier_sigmas > 0:
            spare = None if view is None else steep_echoes(points, view, planes, _STEEP_ECHO_SHADOW_MM)
            keep &= ~planes.outliers(d.outlier_sigmas, 0.1 * d.surface_fit_mm, spare)
        if not keep.any():
            raise InputError(f"{source}: no point has enough neighbours within data.surface_fit_mm = "
                             f"{d.surface_fit_mm:g} mm to form a surface (is the cloud in mm?)")
        if d.denoise:
            points = planes.projected(points)
        if view is not None and d.shadow_mm > 0:  # among the points kept so far
            rows = np.flatnonzero(keep)
            keep[rows[shadowed(points[rows], view[rows], d.shadow_mm)]] = False
        dropped += int((~keep).sum())
        points, planes = points[keep], planes.subset(keep)
        attrs = None if attrs is None else attrs[keep]
    return points, attrs, planes, dropped


@dataclass
class FittedSurface:
    """A method fitted to one cloud, before extraction (:func:`fit`): the method's field or mesh in
    unit space (``fitted``), the one map back to mm (``unit.normalizer``), what the support trim
    measures to (``support``) and the method's hints for the grid extractors (``fitted.surface``,
    ``fitted.normals``)."""

    method: str
    preset: str
    config: Config
    device: torch.device
    seed: int
    fitted: Fitted
    unit: "_UnitCloud" = dataclasses.field(repr=False)
    support: np.ndarray | DataSurface = dataclasses.field(repr=False)
    input: dict[str, Any] = dataclasses.field(default_factory=dict)
    """The sidecar's ``input`` (:func:`input_record`)."""
    started: float = dataclasses.field(default_factory=time.perf_counter, repr=False)

    @property
    def field(self) -> Field | None:
        """The fitted field in unit space; ``None`` for methods that give a mesh directly."""
        return self.fitted.field

    @property
    def normalizer(self) -> Normalizer:
        """The map between the input's millimetres and the unit space of the field."""
        return self.unit.normalizer

    def extract(self, progress: Progress | None = None, **settings: Any) -> trimesh.Trimesh | None:
        """The surface in mm (input frame): the field extracted as the configuration says, with
        ``settings`` replacing fields of its ``extract``, ``clean`` or ``grid`` section (each name
        belongs to one: e.g. ``mode="faithful", max_depth=9, trim_mm=0``, or ``mode="capudf_mc",
        resolution=128``), or the method's own mesh; then the support trim. ``None`` when no surface
        is found."""
        return self._extract(*_with_settings(self.config, settings), progress or Progress(quiet=True))[0]

    def _extract(self, cfg: ExtractConfig, clean: CleanConfig, grid: GridConfig, progress: Progress
                 ) -> tuple[trimesh.Trimesh | None, int, ExtractConfig]:
        """The mesh in mm, the faces the support trim removed and the extraction settings used."""
        cfg = resolve_leaf_size(cfg, self.normalizer)
        if self.fitted.mesh is not None:
            unit_mesh = self.fitted.mesh
        elif self.fitted.field is not None:
            unit_mesh = extract_mesh(self.fitted.field, cfg, progress, surface=self.fitted.surface,
                                     normals=self.fitted.normals, clean=clean, grid=grid)
        else:
            unit_mesh = None
        mesh, trimmed = _trim_and_map(unit_mesh, self.support, self.normalizer, cfg.trim_mm,
                                      cfg.trim_normal_mm)
        return mesh, trimmed, cfg


def _with_settings(config: Config, settings: dict[str, Any]) -> tuple[ExtractConfig, CleanConfig, GridConfig]:
    """The ``extract``, ``clean`` and ``grid`` sections of ``config`` with ``settings`` replacing the
    fields of whichever section holds each name (:class:`TypeError` for a name none holds)."""
    left = dict(settings)
    out = []
    for section in (config.extract, config.clean, config.grid):
        names = {f.name for f in dataclasses.fields(section)}
        out.append(dataclasses.replace(section, **{k: left.pop(k) for k in list(left) if k in names}))
    if left:
        raise TypeError(f"unknown extraction setting(s): {', '.join(left)}")
    return out[0], out[1], out[2]


def _finish(surface: FittedSurface, progress: Progress) -> Reconstruction:
    """Extraction (unless the method gave a mesh), the map back to mm, timings, counts, quality."""
    fitted, unit, cfg, dev = surface.fitted, surface.unit, surface.config, surface.device
    t1 = time.perf_counter()
    mesh, trimmed, extract_cfg = surface._extract(cfg.extract, cfg.clean, cfg.grid, progress)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    extract_s = time.perf_counter() - t1
    t2 = time.perf_counter()
    fit = (data_fit(mesh, unit.normalizer.inverse(unit.points), cfg.extract.fit_mm)
           if mesh is not None and cfg.extract.fit_mm > 0 else {})
    fit_s = time.perf_counter() - t2

    timings = {
        "preprocess_s": unit.voxel_s + unit.surface_fit_s + fitted.timings.get("preprocess_s", 0.0),
        "train_s": fitted.timings.get("train_s", 0.0),
        "extract_s": extract_s,
        "voxel_s": unit.voxel_s,
        "surface_fit_s": unit.surface_fit_s,
        "fit_s": fit_s,
        # the method's own pre-processing steps (e.g. subset_s, sigma_s, static_nn_s)
        **{k: v for k, v in fitted.timings.items() if k not in ("preprocess_s", "train_s")},
    }
    timings["total_s"] = time.perf_counter() - surface.started
    counts = {"input_points": unit.input_points, "voxelized_points": len(unit.points) + unit.outliers,
              "voxel_size_mm": unit.voxel_mm,
              "outliers_removed": unit.outliers, "frames": unit.frames, "extract_depth": extract_cfg.max_depth,
              **fitted.counts,
              "vertices": 0 if mesh is None else len(mesh.vertices),
              "faces": 0 if mesh is None else len(mesh.faces), "trimmed_faces": trimmed}
    quality = mesh_quality(mesh) if mesh is not None else {}
    return Reconstruction(mesh=mesh, method=surface.method, preset=surface.preset, config=cfg, timings=timings,
                          counts=counts, quality=quality, data_fit=fit, device=str(dev), seed=surface.seed,
                          normalizer=unit.normalizer, history=fitted.history, method_info=fitted.info,
                          input=dict(surface.input), surface=surface)


def resolve_leaf_size(cfg: ExtractConfig, normalizer: Normalizer) -> ExtractConfig:
    """``cfg`` with ``max_depth`` lowered until the leaf edge is at least ``cfg.min_leaf_mm`` mm
    (``extract.min_leaf_mm``; never below depth 1), unchanged when that is 0."""
    if cfg.min_leaf_mm <= 0:
        return cfg
    span_mm = (cfg.domain[1] - cfg.domain[0]) * normalizer.scale
    depth = cfg.max_depth
    while depth > 1 and span_mm / 2 ** depth < cfg.min_leaf_mm:
        depth -= 1
    return dataclasses.replace(cfg, max_depth=depth)


def _support(points: np.ndarray, planes: LocalPlanes | None, d: DataConfig) -> np.ndarray | DataSurface:
    """The support trim's reference: the unit-space points, or with local planes the surface
    through them, bridged across their gaps with ``data.bridge`` > 0 and across a sweep's frames with
    ``data.frame_bridge`` (its distance is the distance to the nearest point without; its normals
    serve ``extract.trim_normal_mm``)."""
    if planes is None:
        return points
    return DataSurface.from_planes(points, planes, d.bridge, frame_bridge=d.frame_bridge)


def _trim_and_map(unit_mesh: trimesh.Trimesh | None, support: np.ndarray | DataSurface, normalizer: Normalizer,
                  trim_mm: float, trim_normal_mm: float = 0.0) -> tuple[trimesh.Trimesh | None, int]:
    """The support trim (``extract.trim_mm`` and ``extract.trim_normal_mm``, against the unit-space
    ``support``), then the one map back to mm. Returns the mesh in mm (``None`` when nothing is
    left) and the faces removed."""
    if unit_mesh is None:
        return None, 0
    trimmed = trim_to_support(unit_mesh, support, trim_mm / normalizer.scale,
                              trim_normal_mm / normalizer.scale)
    removed = len(unit_mesh.faces) - (0 if trimmed is None else len(trimmed.faces))
    return (None if trimmed is None else normalizer.inverse_mesh(trimmed)), removed


def _validate_frames(frame_index: Any, probe: np.ndarray | None, source: str) -> np.ndarray | None:
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


def _validate_probe(probe_positions: Any, n_points: int, source: str) -> np.ndarray | None:
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
