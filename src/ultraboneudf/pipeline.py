"""``reconstruct``: points (mm) → pre-processing → method → extraction → mesh (mm).

This is the one place where the cloud is normalised (:class:`Normalizer` fitted on the voxelised
cloud) and the one place where the mesh is mapped back to millimetres. Optional per-point probe
positions (from a tracked sweep) follow the points through voxelisation and the same normalisation.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from ._version import __version__
from .config import Config, apply_overrides, preset as make_preset
from .errors import InputError
from .extraction import extract_mesh, mesh_quality
from .geometry.normalize import Normalizer
from .geometry.voxel import voxel_downsample, voxel_downsample_with
from .io import save_json, save_mesh, validate_points
from .methods import get_method
from .progress import Progress


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
    device: str
    seed: int
    normalizer: Normalizer
    history: dict[str, list[float]] = field(default_factory=dict)
    input: dict[str, Any] = field(default_factory=dict)
    method_info: dict[str, Any] = field(default_factory=dict)
    """Choices the method resolved at run time (e.g. ``poisson_orientation``: ``tangent``/``probe``)."""
    version: str = __version__

    def sidecar(self) -> dict[str, Any]:
        """The JSON sidecar (DESIGN.md): everything needed to trace the mesh to its configuration."""
        return {
            "method": self.method,
            "preset": self.preset,
            "config": self.config.to_dict(),
            "timings": {k: round(v, 4) for k, v in self.timings.items()},
            "counts": self.counts,
            "mesh_quality": self.quality,
            "device": self.device,
            "seed": self.seed,
            "version": self.version,
            "input": self.input,
            "method_info": self.method_info,
            "normalization": self.normalizer.to_dict(),
            "loss_history": self.history,
        }

    def save(self, path: str | Path) -> Path:
        """Write the mesh (format by suffix) and the sidecar ``path.with_suffix('.json')``, atomically.
        Returns the sidecar path."""
        if self.mesh is None:
            raise RuntimeError("no mesh to save: the reconstruction failed")
        path = Path(path)
        sidecar = path.with_suffix(".json")
        save_mesh(self.mesh, path)
        save_json(self.sidecar(), sidecar)
        return sidecar


def resolve_device(device: str | torch.device) -> torch.device:
    """``auto`` → CUDA if available, else CPU; anything else must be usable here."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("device 'cuda' requested but no CUDA device is available (use --device cpu)")
    return dev


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def reconstruct(points_mm: Any, preset: str = "official", device: str | torch.device = "auto",
                seed: int = 42, method: str = "ultraboneudf", *, config: Config | None = None,
                assignments: list[str] | tuple[str, ...] = (), progress: Progress | None = None,
                quiet: bool = True, source: str = "points", probe_positions: Any = None,
                **overrides: Any) -> Reconstruction:
    """Reconstruct a bone surface mesh from a point cloud in millimetres.

    Parameters
    ----------
    points_mm : (N, 3) array-like, millimetres in the input's frame.
    preset : ``official`` (the reference code), ``paper`` (the paper's text) or ``fast``.
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
        ``model.poisson_orientation``); ignored by the others.
    """
    t_start = time.perf_counter()
    progress = progress or Progress(quiet=quiet)
    entry = get_method(method)
    cfg = config if config is not None else make_preset(preset)
    if config is None:
        entry.configure(cfg, preset)  # the method's own defaults, before the user's overrides
    apply_overrides(cfg, overrides, assignments)
    fit = entry.fit
    dev = resolve_device(device)
    points = validate_points(points_mm, source=source)
    probe = _validate_probe(probe_positions, len(points), source)
    seed_everything(seed)

    t0 = time.perf_counter()
    if cfg.data.noise_sigma_mm > 0:
        points = points + np.random.default_rng(seed + 1).normal(0.0, cfg.data.noise_sigma_mm, points.shape)
    voxel_probe = None
    if probe is None:
        voxelised = voxel_downsample(points, cfg.data.voxel_size_mm)
    else:  # each voxel's probe position: the mean of those of its points
        voxelised, voxel_probe = voxel_downsample_with(points, probe, cfg.data.voxel_size_mm)
    normalizer = Normalizer.fit(voxelised)
    unit_points = normalizer.forward(voxelised)
    unit_probe = None if voxel_probe is None else normalizer.forward(voxel_probe)
    voxel_s = time.perf_counter() - t0

    extra = {"probe": unit_probe} if entry.takes_probe else {}
    fitted = fit(unit_points, cfg, dev, seed, progress, **extra)
    t1 = time.perf_counter()
    if fitted.mesh is not None:
        unit_mesh = fitted.mesh
    elif fitted.field is not None:
        unit_mesh = extract_mesh(fitted.field, cfg.extract, progress, surface=fitted.surface,
                                 normals=fitted.normals)
    else:
        unit_mesh = None
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    extract_s = time.perf_counter() - t1
    mesh = normalizer.inverse_mesh(unit_mesh) if unit_mesh is not None else None

    timings = {
        "preprocess_s": voxel_s + fitted.timings.get("preprocess_s", 0.0),
        "train_s": fitted.timings.get("train_s", 0.0),
        "extract_s": extract_s,
        "voxel_s": voxel_s,
        # the method's own pre-processing steps (e.g. subset_s, sigma_s, static_nn_s)
        **{k: v for k, v in fitted.timings.items() if k not in ("preprocess_s", "train_s")},
    }
    timings["total_s"] = time.perf_counter() - t_start
    counts = {"input_points": len(points), "voxelized_points": len(voxelised), **fitted.counts,
              "vertices": 0 if mesh is None else len(mesh.vertices),
              "faces": 0 if mesh is None else len(mesh.faces)}
    quality = mesh_quality(mesh) if mesh is not None else {}
    return Reconstruction(mesh=mesh, method=method, preset=preset if config is None else "custom",
                          config=cfg, timings=timings, counts=counts, quality=quality, device=str(dev), seed=seed,
                          normalizer=normalizer, history=fitted.history, method_info=fitted.info)


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
