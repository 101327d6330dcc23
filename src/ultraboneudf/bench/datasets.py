"""Built-in dataset generators: each writes its inputs, ground truths and a ``manifest.csv``.

- ``openbone``: every bone mesh of a folder cut to the faces that look toward +z (what a probe
  above the bone sees), sampled by area — the paper's OpenBoneCT, from the user's own meshes;
- ``closedbone``: the whole meshes sampled (ClosedBoneCT);
- ``simsweep``: a tracked sweep simulated over every bone at a named noise level, several seeds, its
  compounded points with their probe positions (frames registered to each other, as
  ``reconstruct SWEEP`` does), against the surface the probe saw;
- ``pairs``: a user's folder of ``NAME.<cloud>`` + ``NAME_gt.<mesh>`` pairs.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..io import MESH_SUFFIXES, POINT_READERS, atomic_write_bytes, load_mesh, save_mesh
from ..progress import QUIET, Progress
from .manifest import Unit, write_manifest

KINDS = ("openbone", "closedbone", "simsweep", "pairs")


def _meshes(folder: Path) -> list[Path]:
    found = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES) if folder.is_dir() else []
    if not found:
        raise InputError(f"{folder}: no bone meshes ({', '.join(MESH_SUFFIXES)}) in this folder")
    return found


def _save_points(path: Path, points: np.ndarray, probe: np.ndarray | None = None,
                 frames: np.ndarray | None = None) -> None:
    buf = io.BytesIO()
    np.savez(buf, points=points, **({} if probe is None else {"probe": probe}),
             **({} if frames is None else {"frame": frames}))
    atomic_write_bytes(path, buf.getvalue())


def make_dataset(kind: str, source: str | os.PathLike, out: str | os.PathLike, *, samples: int = 100_000,
                 level: str = "hard", seeds: tuple[int, ...] = (0,), progress: Progress = QUIET) -> Path:
    """Write the dataset ``kind`` made from the meshes (or pairs) in ``source`` into ``out``;
    returns the manifest's path. Lengths in mm; ``samples`` points per open/closed bone; ``level``
    and ``seeds`` for ``simsweep``."""
    import trimesh

    from ..synth import facing_surface

    source, out = Path(source), Path(out)
    if kind not in KINDS:
        raise InputError(f"unknown dataset kind {kind!r}; choose one of {', '.join(KINDS)}")
    out.mkdir(parents=True, exist_ok=True)
    units: list[Unit] = []
    if kind == "pairs":
        units = _pairs(source)
    else:
        meshes = _meshes(source)
        jobs = [(m, s) for m in meshes for s in (seeds if kind == "simsweep" else (0,))]
        with progress.stage(f"dataset {kind}", len(jobs)) as advance:
            for mesh_path, seed in jobs:
                mesh = load_mesh(mesh_path)
                name = mesh_path.stem if kind != "simsweep" else f"{mesh_path.stem}_s{seed}"
                probe = frames = None
                if kind == "openbone":
                    truth = facing_surface(mesh, (0.0, 0.0, 1.0))
                    points = trimesh.sample.sample_surface(truth, samples, seed=seed)[0]
                elif kind == "closedbone":
                    truth = mesh
                    points = trimesh.sample.sample_surface(truth, samples, seed=seed)[0]
                else:
                    from ..sweep.front_end import SweepOptions, sweep_points
                    from ..synth.simulator import config_with_noise, simulate_sweep

                    sim = simulate_sweep(mesh, config_with_noise(level, seed=seed))
                    sp = sweep_points(sim.sweep, SweepOptions(segment="masks"))
                    points, probe, frames, truth = sp.points, sp.probe_position, sp.frame_index, sim.visible_mesh
                _save_points(out / f"{name}.npz", points, probe, frames)
                save_mesh(truth, out / f"{name}_gt.ply")
                units.append(Unit(name, mesh_path.stem, out / f"{name}.npz", out / f"{name}_gt.ply"))
                advance()
    manifest = out / "manifest.csv"
    write_manifest(units, manifest)
    return manifest


def _pairs(folder: Path) -> list[Unit]:
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    units = []
    for cloud in sorted(p for p in folder.iterdir() if p.suffix.lower() in POINT_READERS
                        and not p.stem.endswith("_gt")):
        gts = [folder / f"{cloud.stem}_gt{s}" for s in MESH_SUFFIXES]
        gt = next((g for g in gts if g.exists()), None)
        if gt is not None:
            units.append(Unit(cloud.stem, cloud.stem, cloud.resolve(), gt.resolve()))
    if not units:
        raise InputError(f"{folder}: no NAME.<cloud> with a NAME_gt.<mesh> beside it")
    return units
