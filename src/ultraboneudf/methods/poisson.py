"""Screened Poisson surface reconstruction (§7): depth 9 on the pre-processed cloud with the
UltraBoneUDF normal recipe (§7.2), no density trimming.

Normal orientation (``poisson.orientation``): tangent-plane propagation (the default recipe),
or, when the input carries per-point probe positions (a sweep), each normal turned toward the probe
that imaged its point (§7.2 alternative B), which stays consistent across gaps between slices.

The solver comes from an optional extra (``pip install 'ultraboneudf[poisson]'``); it is imported
only when the method runs. Backends: ``pymeshlab`` (the extra's choice: one wheel, NumPy its only
dependency) and ``open3d`` (the paper's library; a heavier install). ``poisson.backend=auto``
uses the first one installed, in that order.
"""

from __future__ import annotations

import time

import numpy as np
import torch
import trimesh

from ..config import Config
from ..errors import InputError
from ..geometry.normals import orient_tangent_plane, orient_toward, pca_normals
from ..geometry.queries import surface_subset_index
from ..progress import QUIET, Progress
from .base import Fitted

BACKENDS = ("pymeshlab", "open3d")
ORIENTATIONS = ("auto", "tangent", "probe")
INSTALL_HINT = ("the poisson method needs a screened-Poisson library: pip install 'ultraboneudf[poisson]' "
                "(installs pymeshlab), or pip install open3d and --set poisson.backend=open3d")


def configure(cfg: Config) -> None:
    """Nothing to train: the preset's data settings pick the input cloud (§7.1)."""
    cfg.train.iters = 0


def resolve_orientation(name: str, has_probe: bool) -> str:
    """The orientation for ``poisson.orientation``: ``tangent`` or ``probe`` (``auto`` →
    ``probe`` when probe positions are present, else ``tangent``). Raises :class:`InputError` for an
    unknown choice, or for ``probe`` without probe positions."""
    if name not in ORIENTATIONS:
        raise InputError(f"unknown poisson.orientation {name!r}; choose {', '.join(ORIENTATIONS)}")
    if name == "auto":
        return "probe" if has_probe else "tangent"
    if name == "probe" and not has_probe:
        raise InputError("poisson.orientation=probe needs per-point probe positions: reconstruct a "
                         "tracked sweep, or pass probe_positions= to reconstruct()")
    return name


def estimate_normals(surface: np.ndarray, cloud: np.ndarray, rule: str,
                     viewpoints: np.ndarray | None = None) -> np.ndarray:
    """Oriented normals of ``surface`` (§7.2): ``ultraboneudf`` (PCA radius 0.5 ≤ 1,000 neighbours
    on ``cloud``) or ``knn30`` (PCA over the 30 nearest points), then oriented by tangent-plane
    propagation with 15 neighbours, or, given ``viewpoints`` (N, 3) (the probe position of each
    surface row), each turned toward its viewpoint (alternative B)."""
    if rule == "ultraboneudf":
        raw = pca_normals(surface, cloud, radius=0.5, max_nn=1_000)
    elif rule == "knn30":
        raw = pca_normals(surface, cloud, radius=np.inf, max_nn=30)
    else:
        raise InputError(f"unknown poisson.normals {rule!r}; choose ultraboneudf or knn30")
    if viewpoints is not None:
        return orient_toward(surface, raw, viewpoints)
    return orient_tangent_plane(surface, raw, 15)


def _pymeshlab(points: np.ndarray, normals: np.ndarray, depth: int, scale: float, threads: int
               ) -> tuple[np.ndarray, np.ndarray]:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, scale=scale, preclean=False,
                                                        threads=threads)
    m = ms.current_mesh()
    return np.asarray(m.vertex_matrix(), dtype=float), np.asarray(m.face_matrix(), dtype=np.int64)


def _open3d(points: np.ndarray, normals: np.ndarray, depth: int, scale: float, threads: int
            ) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    mesh, _densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, width=0, scale=scale, linear_fit=False, n_threads=threads)
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.triangles, dtype=np.int64)


def _available(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def resolve_backend(name: str) -> str:
    """The backend to use for ``poisson.backend``; raises :class:`InputError` with the install
    command when none (or not the requested one) is installed."""
    if name == "auto":
        for candidate in BACKENDS:
            if _available(candidate):
                return candidate
        raise InputError(INSTALL_HINT)
    if name not in BACKENDS:
        raise InputError(f"unknown poisson.backend {name!r}; choose auto, {', '.join(BACKENDS)}")
    if not _available(name):
        raise InputError(f"poisson.backend={name} is not installed: pip install {name} "
                         f"(or use the default: pip install 'ultraboneudf[poisson]')")
    return name


def screened_poisson(points: np.ndarray, normals: np.ndarray, depth: int = 9, scale: float = 1.1,
                     backend: str = "auto", threads: int = 0) -> trimesh.Trimesh | None:
    """Screened Poisson mesh of oriented ``points``/``normals`` (N, 3) at octree ``depth``; library
    defaults otherwise (width 0, no linear fit). ``threads`` < 1: ``torch.get_num_threads()``.
    ``None`` when empty."""
    name = resolve_backend(backend)
    if threads < 1:
        threads = max(1, torch.get_num_threads())
    run = _pymeshlab if name == "pymeshlab" else _open3d
    v, f = run(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
               depth, scale, threads)
    if not len(f):
        return None
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def fit(points: np.ndarray, cfg: Config, device: torch.device, seed: int,
        progress: Progress = QUIET, *, probe: np.ndarray | None = None) -> Fitted:
    """Poisson on the preset's surface subset of the unit-space cloud (scale-invariant, §7.3);
    returns a unit-space mesh. ``probe`` (N, 3), unit space: the probe position of each row of
    ``points``, used by the ``probe`` orientation."""
    orientation = resolve_orientation(cfg.poisson.orientation, probe is not None)
    backend = resolve_backend(cfg.poisson.backend)  # fail before any work when missing
    if probe is not None and np.shape(probe) != np.shape(points):
        raise InputError(f"probe positions have shape {np.shape(probe)}, expected {np.shape(points)} "
                         f"(one per point)")
    d = cfg.data
    t0 = time.perf_counter()
    with progress.stage("normals", 1) as advance:
        rows = surface_subset_index(points, d.subset, d.subset_threshold, d.fps_sizes, d.max_points,
                                    device=str(device))
        rows = np.arange(len(points)) if rows is None else rows
        # duplicated FPS rows (official subset) would only double-weight points in the solver
        surface, first = np.unique(points[rows], axis=0, return_index=True)
        viewpoints = probe[rows[first]] if orientation == "probe" else None
        normals = estimate_normals(surface, points, cfg.poisson.normals, viewpoints)
        advance()
    prep_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    with progress.stage(f"screened poisson ({backend}, depth {cfg.poisson.octree_depth})", 1) as advance:
        mesh = screened_poisson(surface, normals, cfg.poisson.octree_depth, cfg.poisson.scale, backend,
                                threads=cfg.poisson.solver_threads)
        advance()
    return Fitted(mesh=mesh, counts={"surface_points": len(surface), "queries": 0, "parameters": 0},
                  timings={"preprocess_s": prep_s, "train_s": time.perf_counter() - t1},
                  surface=surface, normals=normals,
                  info={"poisson_orientation": orientation, "poisson_backend": backend})
