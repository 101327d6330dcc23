"""Tracked freehand sweep simulator with known truth.

Given a closed bone mesh (mm), :func:`simulate_sweep` moves a linear probe along the bone and
produces, per frame: the B-mode-like image, the true bone mask, a "predicted" mask with the errors
of a real segmentation network, and the probe pose with tracking noise. It also returns the
visible ground-truth surface (the mesh faces seen by at least one beam, the paper's OpenBoneCT
truth) next to the closed mesh. :meth:`SimulatedSweep.write` stores it all in the UltraBones100k
sample layout, so every reader and the whole pipeline run on it unchanged.

The stages, each a module of its own (all lengths in mm):

* :mod:`.probe_path`: the true poses along the bone, the tracker's noisy record of them, and the
  runs of frames a sweep loses. Frames come at ``frame_rate_hz``.
* :mod:`.beams`: each image column's first hit on the bone and its incidence angle; a surface hit
  above ``max_incidence_deg`` returns no echo and is not part of the visible truth.
* :mod:`.bmode`: the B-mode-like image of a frame.
* :mod:`.mask_errors`: the "predicted" masks, with a segmentation network's errors.
* :mod:`.visible_truth`: the faces of the mesh the beams see.

This module runs them in order. One random stream (the seed) feeds the path, the fascia, each
frame's image then mask, the tracking noise and the lost frames, in that order; the clutter of the
``real`` level draws from a second stream, so the other levels stay as they were before it.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from .._version import __version__
from ..errors import InputError
from ..io import atomic_write_bytes, save_json
from ..progress import QUIET, Progress
from ..sweep.model import Sweep
from ..sweep.formats import ultrabones
from ..sweep.transforms import pixels_to_world, rigid_from_euler
from .beams import ImageSlicer, incidence
from .bmode import bmode_image, fascia_depths, make_fascia
from .mask_errors import add_clutter, boundary_offsets, predicted_mask
from .probe_path import missing_frames, perturb_poses, plan_path
from .simulation_config import NOISE_PRESETS, SimulationConfig, config_with_noise
from .slicing import MeshArrays
from .visible_truth import visible_truth

DEFAULT_CALIBRATION = rigid_from_euler([26.0, -0.5, 128.0], [92.5, -0.5, 179.2])
"""A probe calibration like the UltraBones100k sample's (image-plane mm → probe frame)."""


@dataclass
class SimulatedSweep:
    """Output of :func:`simulate_sweep`.

    Attributes:
        sweep: the recorded sweep: images ``(F, H, W)`` uint8, predicted masks, poses *with*
            tracking noise, pixel offset 0.5 (UltraBones100k convention).
        true_image_to_world: ``(F, 4, 4)`` exact poses.
        true_masks: ``(F, H, W)`` bool, the visible bone surface pixel of each scan line.
        pred_masks: ``(F, H, W)`` bool, the "predicted" masks (same as ``sweep.masks``).
        surface_depth_mm: ``(F, W)`` first-hit depth along each beam (inf: no bone), mm.
        incidence_deg: ``(F, W)`` incidence angle of the first hit (nan: no bone).
        calibration: ``(4, 4)`` rigid probe calibration used to write ``poses.csv``.
        visible_mesh: the visible ground-truth surface (open mesh, mm).
        closed_mesh: the input closed mesh.
        config: the configuration used.
    """

    sweep: Sweep
    true_image_to_world: np.ndarray
    true_masks: np.ndarray
    pred_masks: np.ndarray
    surface_depth_mm: np.ndarray
    incidence_deg: np.ndarray
    calibration: np.ndarray
    visible_mesh: trimesh.Trimesh
    closed_mesh: trimesh.Trimesh
    config: SimulationConfig
    info: dict[str, Any] = field(default_factory=dict)

    def true_sweep(self) -> Sweep:
        """The same frames with the exact poses and the true masks."""
        return self.sweep.replace(image_to_world=self.true_image_to_world, masks=self.true_masks)

    def true_positions(self, frame_index: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """``(N, 3)`` mm: where the pixels ``pixel`` ``(N, 2)`` (column, row) of the frames
        ``frame_index`` ``(N,)`` lie under the exact poses; compounded with the recorded poses
        they are off by the tracking error."""
        p2w = self.true_sweep().pixel_to_world()
        out = np.empty((len(pixel), 3))
        for f in np.unique(frame_index):
            rows = frame_index == f
            out[rows] = pixels_to_world(p2w[f], pixel[rows, 0], pixel[rows, 1])
        return out

    def write(self, folder: str | os.PathLike) -> Path:
        """Write the sweep folder (see :func:`write_simulation`)."""
        return write_simulation(self, folder)


def simulate_sweep(mesh: trimesh.Trimesh, config: SimulationConfig | None = None,
                   progress: Progress = QUIET, calibration: np.ndarray | None = None) -> SimulatedSweep:
    """Simulate a tracked freehand sweep over a closed bone mesh (mm). See the module docstring.

    Raises:
        InputError: for an empty or non-watertight mesh, or a path that misses the bone.
    """
    cfg = config or SimulationConfig()
    if len(mesh.faces) == 0:
        raise InputError("the bone mesh has no faces")
    if not mesh.is_watertight:
        raise InputError("the bone mesh is not closed (watertight); the simulator needs a closed "
                         "surface to tell the bone's inside from its outside")
    rng = np.random.default_rng(cfg.seed)
    arrays = MeshArrays.from_mesh(mesh)
    poses, path_info = plan_path(mesh, cfg, arrays, rng)
    n, h, w = len(poses), cfg.height_px, cfg.width_px
    xs = (np.arange(w) + 0.5) * cfg.spacing_mm
    slicer = ImageSlicer(arrays, np.asarray(path_info["sweep_axis"]), cfg)
    fascia = make_fascia(rng, cfg)
    images = np.zeros((n, h, w), dtype=np.uint8)
    true_masks = np.zeros((n, h, w), dtype=bool)
    pred_masks = np.zeros((n, h, w), dtype=bool)
    depths = np.full((n, w), np.inf)
    incid = np.full((n, w), np.nan)
    clutter = np.random.default_rng([cfg.seed, 1])  # its own stream: the other levels stay as they were
    offset_px = boundary_offsets(clutter, n, cfg)
    with progress.stage("simulate", n) as advance:
        for k in range(n):
            depth, face = slicer.hits(poses[k], xs)
            inc = incidence(arrays, face, poses[k, :3, 1])
            depth = np.where(depth < h * cfg.spacing_mm, depth, np.inf)
            inc = np.where(np.isfinite(depth), inc, np.nan)
            depths[k], incid[k] = depth, inc
            visible = np.isfinite(depth) & (np.nan_to_num(inc, nan=180.0) <= cfg.max_incidence_deg)
            rows = np.where(visible, np.floor(depth / cfg.spacing_mm), np.nan)
            cols = np.flatnonzero(visible)
            true_masks[k, rows[cols].astype(np.int64), cols] = True
            fy = fascia_depths(fascia, xs, k)
            images[k] = bmode_image(depth, inc, fy, fascia, cfg, rng)
            pred_masks[k] = predicted_mask(rows, inc, fy, cfg, rng, offset_px[k])
            advance(1)
    add_clutter(pred_masks, depths, fascia, xs, float(path_info["mean_frame_spacing_mm"]), cfg, clutter)
    recorded = perturb_poses(poses, cfg, rng)
    visible_mesh, beam_mm = visible_truth(mesh, poses, slicer, cfg, progress)
    calib = DEFAULT_CALIBRATION if calibration is None else np.asarray(calibration, dtype=np.float64)
    stamps = np.rint(np.arange(n) * 1000.0 / cfg.frame_rate_hz)
    sweep = Sweep(image_to_world=recorded, spacing_mm=(cfg.spacing_mm, cfg.spacing_mm),
                  image_size=(w, h), images=images, masks=pred_masks, timestamps=stamps,
                  frame_names=[f"{int(t)}.png" for t in stamps], pixel_offset=0.5, orientation="MF",
                  source="simulation", meta={"layout": "ultrabones", "calibration": calib})
    kept = np.flatnonzero(~missing_frames(poses, cfg, rng))
    info = dict(path_info)
    info.update(frames=int(len(kept)), missing_frames=int(n - len(kept)),
                visible_faces=int(len(visible_mesh.faces)), truth_beam_mm=beam_mm,
                visible_area_mm2=float(visible_mesh.area) if len(visible_mesh.faces) else 0.0,
                bone_columns_fraction=float(np.isfinite(depths[kept]).mean()),
                true_mask_pixels=int(true_masks[kept].sum()), pred_mask_pixels=int(pred_masks[kept].sum()))
    return SimulatedSweep(sweep=sweep.subset(kept), true_image_to_world=poses[kept],
                          true_masks=true_masks[kept], pred_masks=pred_masks[kept],
                          surface_depth_mm=depths[kept], incidence_deg=incid[kept],
                          calibration=calib, visible_mesh=visible_mesh, closed_mesh=mesh,
                          config=cfg, info=info)


SIM_README = """# Simulated tracked ultrasound sweep (ultraboneudf simulate)

Layout of the UltraBones100k sample (`ultraboneudf sweep2points` and `reconstruct` read it as is):

| path | what |
| --- | --- |
| `frames/<t>.png` | B-mode-like frames, 8-bit grey |
| `masks/<t>.png` | "predicted" bone masks with realistic errors (gaps, false positives, jitter) |
| `masks_true/<t>.png` | true masks: the visible bone surface pixel of each scan line |
| `poses.csv`, `calibration.json` | probe poses *with tracking noise* and the probe calibration |
| `truth/poses.csv`, `truth/calibration.json` | the exact poses |
| `gt_visible.ply` | visible ground-truth surface: mesh faces seen by at least one beam (mm) |
| `gt_closed.ply` | the closed bone mesh (mm) |
| `simulation.json` | the simulator's configuration, seed, version and counts |

Pixel → world (mm): `T_track · T_calib · diag(s, s, 1, 1) · [c + 0.5, r + 0.5, 0, 1]ᵀ` with Euler
angles extrinsic xyz in degrees, as in the UltraBones100k sample. The world frame is the mesh's.
"""


def write_simulation(sim: SimulatedSweep, folder: str | os.PathLike) -> Path:
    """Write a simulated sweep in the UltraBones100k layout plus its truth (every file atomic)."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    names = [str(int(t)) for t in sim.sweep.timestamps]
    ultrabones.write(sim.sweep, out, calibration=sim.calibration, names=names,
                     mask_sets={"masks": sim.pred_masks, "masks_true": sim.true_masks})
    ultrabones.write(sim.true_sweep().with_masks(None), out / "truth", calibration=sim.calibration,
                     names=names, write_images=False)
    for name, mesh in (("gt_visible.ply", sim.visible_mesh), ("gt_closed.ply", sim.closed_mesh)):
        data = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
        atomic_write_bytes(out / name, data)
    meta = {"generator": f"ultraboneudf {__version__} simulate", "config": asdict(sim.config),
            "info": sim.info, "pixel_offset": 0.5,
            "files": {"frames": "frames/", "predicted_masks": "masks/", "true_masks": "masks_true/",
                      "poses_recorded": "poses.csv", "poses_true": "truth/poses.csv",
                      "visible_gt": "gt_visible.ply", "closed_gt": "gt_closed.ply"}}
    save_json(json.loads(json.dumps(meta, default=float)), out / "simulation.json")
    atomic_write_bytes(out / "README.md", SIM_README.encode("utf-8"))
    return out


def load_bone_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Read a closed bone mesh for the simulator (InputError naming the file if unusable)."""
    from ..io import load_mesh  # noqa: PLC0415

    mesh = load_mesh(path)
    if not mesh.is_watertight:
        raise InputError(f"{path}: the mesh is not closed (watertight); the simulator needs a closed "
                         f"bone surface")
    return mesh


__all__ = ["SimulationConfig", "SimulatedSweep", "simulate_sweep", "write_simulation",
           "config_with_noise", "NOISE_PRESETS", "DEFAULT_CALIBRATION", "load_bone_mesh"]
