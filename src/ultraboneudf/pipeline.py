"""``reconstruct``: points (mm) → pre-processing → method → extraction → mesh (mm).

The pre-processing in mm and the normalisation into unit space are :func:`~.preprocess.prepare`'s
(optional per-point probe positions and frames of a tracked sweep follow the points); this module
resolves the configuration, fits the method, extracts the mesh and maps it back to millimetres with
the inverse of that one normalisation (:func:`_trim_and_map`).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import random
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Sequence

import numpy as np
import torch
import trimesh

from ._version import __version__
from .checkpoints import Checkpoint
from .config import (DEFAULT_PRESET, CleanConfig, Config, ExtractConfig, GridConfig, apply_overrides,
                     preset as make_preset, validate)
from .devices import resolve_device
from .errors import FitWarning, InputError
from .evaluation.data_fit import data_fit
from .extraction import extract_mesh, grazing_faces, mesh_quality, trim_to_support, without_faces
from .fields.base import Field
from .geometry.normalize import Normalizer
from .geometry.data_surface import DataSurface
from .geometry.surface_fit import LocalPlanes
from .io import check_outputs, save_mesh_with_sidecar
from .methods import Fitted, get_method
from .methods import ultraboneudf as ubu
from .preprocess import UnitCloud, prepare
from .progress import Progress

FIT_LIMIT = 0.01
"""A ``data_fit`` fraction above this is a :class:`FitIssue`."""


@dataclass(frozen=True)
class FitIssue:
    """One way a mesh does not fit its input, from its ``data_fit`` figures
    (:func:`~ultraboneudf.evaluation.data_fit.data_fit`); each front end phrases it for its users
    (:func:`python_text`; the command line its own)."""

    kind: Literal["input_far", "mesh_far"]
    """``input_far``: input points far from the mesh; ``mesh_far``: mesh area far from every input
    point."""
    value: float
    """The share measured: of the input points (``input_far``) or of the mesh area (``mesh_far``)."""
    threshold: float
    """The share above which it is an issue."""
    distance_mm: float
    """How far counts as far, mm (``extract.fit_mm``)."""
    cause: Literal["fit", "unsupported", "bridged"]
    """``fit``: the field did not fit there, the mesh stops short of the data's rim, or the points
    are outliers; ``unsupported``: surface the data does not support; ``bridged``: surface
    interpolated across gaps in the data (``data.bridge``)."""
    setting: tuple[str, float] | None = None
    """A configuration key and the value that addresses the issue (``("extract.trim_mm", 3.0)``)."""
    effect: str = ""
    """What that value does (``removes it``)."""
    retry: tuple[str, ...] = ()
    """Run arguments another value of which may avoid the issue (``seed``, ``preset``)."""
    units: str = "fraction"

    def describe(self) -> str:
        """What was measured and what it means, without advice (the same for every audience)."""
        share, d = f"{100 * self.value:.1f}%", f"{self.distance_mm:g} mm"
        if self.kind == "input_far":
            return (f"{share} of the input points are more than {d} from the mesh (the field did not fit "
                    "there, the mesh stops short of the data's rim, or the points are outliers)")
        what = ("surface interpolated across gaps in the data (data.bridge)" if self.cause == "bridged"
                else "surface the data does not support")
        return f"{share} of the mesh area is {d} or more from every input point: {what}"

    def text(self, argument: Callable[[str], str], setting: Callable[[str, float], str]) -> str:
        """:meth:`describe` and the advice, each name spelled by a front end: ``argument(name)``
        for a run argument (``seed``), ``setting(key, value)`` for a configuration value."""
        text = self.describe()
        if self.retry:
            text += "; try another " + " or ".join(argument(name) for name in self.retry)
        if self.setting is not None:
            text += f"; {setting(*self.setting)} {self.effect}"
        return text


def python_text(issue: FitIssue) -> str:
    """``issue`` for Python users: the advice as arguments of :func:`reconstruct` (``seed=``,
    ``extract__trim_mm=3``)."""
    return issue.text(lambda name: f"{name}=", lambda key, value: f"{key.replace('.', '__')}={value:g}")


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
        """What the support trim (``extract.trim_mm``, ``trim_normal_mm``, ``trim_rim_mm``) measures distances
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

    def fit_issues(self, limit: float = FIT_LIMIT) -> list[FitIssue]:
        """The ways the mesh does not fit its input (``data_fit`` figures above ``limit``, a fraction):
        input the mesh does not reach, mesh area far from every input point. Empty when the mesh
        fits, or when the figures are off (``extract.fit_mm = 0``)."""
        fit, out = self.data_fit, []
        if not fit:
            return out
        t = fit["threshold_mm"]
        if fit["input_far_fraction"] > limit:
            out.append(FitIssue("input_far", fit["input_far_fraction"], limit, t, "fit", retry=("seed", "preset")))
        if fit["mesh_far_area_fraction"] > limit:
            if self.config.extract.trim_mm <= 0:
                issue = FitIssue("mesh_far", fit["mesh_far_area_fraction"], limit, t, "unsupported",
                                 setting=("extract.trim_mm", t), effect="removes it")
            elif self.config.data.bridge > 0:
                issue = FitIssue("mesh_far", fit["mesh_far_area_fraction"], limit, t, "bridged",
                                 setting=("data.bridge", 0.0), effect="leaves the gaps open")
            else:
                issue = FitIssue("mesh_far", fit["mesh_far_area_fraction"], limit, t, "unsupported")
            out.append(issue)
        return out

    def fit_warnings(self, limit: float = FIT_LIMIT) -> list[str]:
        """:meth:`fit_issues` as sentences for Python users (the text of the
        :class:`~ultraboneudf.errors.FitWarning` that :func:`reconstruct` issues), the advice spelled
        as arguments of :func:`reconstruct` (``seed=``, ``extract__trim_mm=``)."""
        return [python_text(issue) for issue in self.fit_issues(limit)]

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


def reconstruct(points_mm: Any, preset: str | None = None, device: str | torch.device = "auto",
                seed: int = 42, method: str = "ultraboneudf", *, config: Config | None = None,
                assignments: list[str] | tuple[str, ...] = (), progress: Progress | None = None,
                quiet: bool = True, source: str = "points", probe_positions: Any = None,
                frame_index: Any = None, checkpoint: Checkpoint | None = None, warn: bool = True,
                **overrides: Any) -> Reconstruction:
    """Reconstruct a bone surface mesh from a point cloud in millimetres.

    Parameters
    ----------
    points_mm : (N, 3) array-like, millimetres in the input's frame.
    preset : ``robust`` (the default: ultrasound-like points), ``fast`` (clean, dense clouds),
        ``official`` (the reference code) or ``paper`` (the paper's text); see
        :data:`~ultraboneudf.config.PRESET_HELP`. With ``config``, only the name the result
        records (``custom`` when not given).
    device : ``auto``, ``cpu``, ``cuda`` or a torch device.
    seed : seeds every random draw; same input, config, seed and device give the same mesh.
    method : a name from :data:`ultraboneudf.methods.METHODS`; its ``configure`` sets the method's
        own defaults (network, loss, schedule, extractor) on the preset before the overrides.
    config : a complete :class:`Config` to use instead of the preset, taken as it is (no method
        defaults applied): :func:`configure` gives one, ``rec.config`` is one.
    assignments, overrides : ``"section.key=value"`` strings and keyword overrides of the preset
        (``iters=1000``, ``extract__max_depth=8``).
    progress / quiet : a :class:`Progress` to report to, or ``quiet=False`` for a default one.
    source : the name used in error messages (a file name).
    probe_positions : optional (N, 3) array-like, mm in the same frame as ``points_mm``: row ``i`` is
        the position of the probe that imaged point ``i`` (``SweepPoints.probe_position`` from
        :func:`ultraboneudf.sweep_points`). Voxel-averaged with the points and normalised
        with the same map. Used by methods that can (Poisson orients its normals toward the probe,
        ``poisson.orientation``); ignored by the others.
    frame_index : optional (N,) integers, with ``probe_positions``: the frame (image) that imaged
        each point (``SweepPoints.frame_index``). The surface through the data then bridges the
        gaps between consecutive frames further than those inside one, and does not reach past the
        sweep's first and last image planes (``data.frame_bridge``).
    checkpoint : save the training's state every ``checkpoint.every`` steps to ``checkpoint.path``
        and, with ``checkpoint.resume``, continue a killed run from it (same result as an
        uninterrupted run); for the methods that train with the shared loop (not FUNSR or Poisson).
    warn : issue each of the result's :meth:`~Reconstruction.fit_issues` as a
        :class:`~ultraboneudf.errors.FitWarning` (a front end that phrases them itself says no).
    """
    progress = progress or Progress(quiet=quiet)
    surface = fit(points_mm, preset, device, seed, method, config=config, assignments=assignments,
                  progress=progress, source=source, probe_positions=probe_positions, frame_index=frame_index,
                  checkpoint=checkpoint, **overrides)
    rec = _finish(surface, progress)
    if warn:
        _warn_fit(rec, source)
    return rec


def fit(points_mm: Any, preset: str | None = None, device: str | torch.device = "auto",
        seed: int = 42, method: str = "ultraboneudf", *, config: Config | None = None,
        assignments: list[str] | tuple[str, ...] = (), progress: Progress | None = None,
        quiet: bool = True, source: str = "points", probe_positions: Any = None,
        frame_index: Any = None, checkpoint: Checkpoint | None = None, **overrides: Any) -> "FittedSurface":
    """The first half of :func:`reconstruct` (same arguments): pre-process, normalise and fit the
    method, without extracting a mesh. :meth:`FittedSurface.extract` then gives the surface in mm,
    as often as wanted and with any extraction settings."""
    started = time.perf_counter()
    progress = progress or Progress(quiet=quiet)
    cfg = configure(preset or DEFAULT_PRESET, method, overrides, assignments, config=config,
                    checkpoint=checkpoint is not None)
    entry = get_method(method)
    dev = resolve_device(device)
    seed_everything(seed)
    points, unit = prepare(points_mm, cfg, seed, source, probe_positions, frame_index)
    extra = {"probe": unit.probe} if entry.takes_probe else {}
    if entry.takes_planes:
        extra["planes"] = unit.planes
    if checkpoint is not None:
        extra["checkpoint"] = checkpoint
    fitted = entry.fit(unit.points, cfg, dev, seed, progress, **extra)
    name = (preset or "custom") if config is not None else (preset or DEFAULT_PRESET)
    return FittedSurface(method=method, preset=name, config=cfg, device=dev,
                         seed=seed, fitted=fitted, unit=unit,
                         support=unit.support(cfg.data), input=input_record(points, source), started=started)


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
    cfg = configure(preset, "ultraboneudf", overrides, assignments)
    dev = resolve_device(device)
    units, records = [], []
    for cloud, name in zip(clouds, names):
        seed_everything(seed)
        cloud, unit = prepare(cloud, cfg, seed, name)
        units.append(unit)
        records.append(input_record(cloud, name))
    fitted = ubu.fit_many([u.points for u in units], cfg, dev, seed, progress, [u.planes for u in units])
    out = [_finish(FittedSurface(method="ultraboneudf", preset=preset, config=cfg, device=dev, seed=seed, fitted=f,
                                 unit=unit, support=unit.support(cfg.data),
                                 input=record, started=t_start), progress)
           for f, unit, record in zip(fitted, units, records)]
    for rec, name in zip(out, names):
        rec.timings["total_s"] = time.perf_counter() - t_start   # the batch's wall time, shared
        _warn_fit(rec, name)
    return out


def configure(preset: str = DEFAULT_PRESET, method: str = "ultraboneudf",
              overrides: Mapping[str, Any] | None = None, assignments: list[str] | tuple[str, ...] = (), *,
              config: Config | None = None, checkpoint: bool = False) -> Config:
    """The complete configuration of a run of ``method``, which :func:`reconstruct` (``config=``)
    takes as it is: ``preset`` with the method's own defaults (network, loss, schedule, extractor),
    then the keyword ``overrides`` (``{"train.iters": 1000}``) and the ``"section.key=value"``
    ``assignments``, validated. With ``config`` (a complete configuration, e.g. an earlier result of
    this function) a copy of it takes the overrides instead: no method defaults are applied again.
    ``checkpoint``: the run will save its training's state; :class:`InputError` for a method whose
    training cannot (the one check of it)."""
    entry = get_method(method)
    if checkpoint and not entry.takes_checkpoint:
        raise InputError(f"method {method} cannot checkpoint its training (it does not train in the shared loop)")
    if config is not None:
        cfg = copy.deepcopy(config)
    else:
        cfg = make_preset(preset)
        entry.configure(cfg)  # the method's own defaults, before the user's overrides
    apply_overrides(cfg, overrides, assignments)
    return validate(cfg, trains=entry.trains)


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
    unit: UnitCloud = dataclasses.field(repr=False)
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
        cfg = resolve_margin(resolve_leaf_size(cfg, self.normalizer), self.fitted.field, self.unit.points)
        cfg = resolve_normal_trim(cfg, self.unit.planes, self.normalizer.scale)
        if self.fitted.mesh is not None:
            unit_mesh = self.fitted.mesh
        elif self.fitted.field is not None:
            unit_mesh = extract_mesh(self.fitted.field, cfg, progress, surface=self.fitted.surface,
                                     normals=self.fitted.normals, clean=clean, grid=grid)
        else:
            unit_mesh = None
        mesh, trimmed = _trim_and_map(unit_mesh, self.support, self.normalizer, cfg, self.unit)
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
              "voxel_size_mm": unit.voxel_mm, "plane_radius_mm": unit.plane_radius_mm,
              "outliers_removed": unit.outliers, "frames": unit.frames,
              "order_frames": unit.order_frames, "extract_depth": extract_cfg.max_depth,
              "extract_margin": extract_cfg.margin, "trim_normal_mm": extract_cfg.trim_normal_mm,
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


def resolve_margin(cfg: ExtractConfig, field: Field | None, points: np.ndarray) -> ExtractConfig:
    """``cfg`` with ``margin`` raised to ``cfg.data_margin`` × the 90th percentile of the unit-space
    ``field`` at the pre-processed ``points`` (N, 3; unit space), where that is larger
    (``extract.data_margin``); unchanged when that is 0 or there is no field."""
    if cfg.data_margin <= 0 or field is None or len(points) == 0:
        return cfg
    u = field.value(torch.as_tensor(points, dtype=torch.float64), chunk=cfg.batch).numpy()
    above = float(np.quantile(u, _DATA_QUANTILE))
    return dataclasses.replace(cfg, margin=max(cfg.margin, cfg.data_margin * above))


_DATA_QUANTILE = 0.9  # most of the data, not the stray points the field was never meant to reach


def resolve_normal_trim(cfg: ExtractConfig, planes: LocalPlanes | None, scale: float) -> ExtractConfig:
    """``cfg`` with ``trim_normal_mm`` lowered to ``cfg.trim_normal_sigmas`` × the median spread of
    the points about their local ``planes`` (unit space; ``scale``: mm per unit), where that is
    smaller, but not under ``_TRIM_NORMAL_FLOOR_MM`` (``extract.trim_normal_sigmas``); unchanged when
    that is 0, the trim is off or there are no planes."""
    if cfg.trim_normal_sigmas <= 0 or cfg.trim_normal_mm <= 0 or planes is None or not planes.valid.any():
        return cfg
    spread_mm = float(np.median(planes.spread[planes.valid])) * scale
    trim = max(_TRIM_NORMAL_FLOOR_MM, cfg.trim_normal_sigmas * spread_mm)
    return dataclasses.replace(cfg, trim_normal_mm=min(cfg.trim_normal_mm, trim))


_GRAZING_RADIUS_MM = 3.0  # the echoes around a face: within about a local plane's radius (data.surface_fit_mm)
_TRIM_NORMAL_FLOOR_MM = 0.4  # on clean points the field's extracted zero set strays this far from the data


def _trim_and_map(unit_mesh: trimesh.Trimesh | None, support: np.ndarray | DataSurface, normalizer: Normalizer,
                  cfg: ExtractConfig, unit: UnitCloud) -> tuple[trimesh.Trimesh | None, int]:
    """The support trim (``extract.trim_mm``, ``trim_normal_mm`` and ``trim_rim_mm``, against the unit-space
    ``support``) and the grazing trim (``trim_grazing_deg``, by the beams of ``unit``'s points), then
    the one map back to mm. Returns the mesh in mm (``None`` when nothing is left) and the faces
    removed."""
    if unit_mesh is None:
        return None, 0
    trimmed = trim_to_support(unit_mesh, support, cfg.trim_mm / normalizer.scale,
                              cfg.trim_normal_mm / normalizer.scale, cfg.trim_rim_mm / normalizer.scale)
    if trimmed is not None and cfg.trim_grazing_deg > 0 and unit.beams is not None:
        trimmed = without_faces(trimmed, grazing_faces(trimmed, unit.points, unit.beams,
                                                       _GRAZING_RADIUS_MM / normalizer.scale, cfg.trim_grazing_deg))
    removed = len(unit_mesh.faces) - (0 if trimmed is None else len(trimmed.faces))
    return (None if trimmed is None else normalizer.inverse_mesh(trimmed)), removed
