"""``register(ct, target)``: the rigid pose of a CT bone in the ultrasound's frame, from any start.

The steps (docs/registration.md):

1. the CT mesh is sampled and its distance grid built (:mod:`.model`); the target (a cloud, or a
   mesh's area samples) is thinned and given local planes (:mod:`.target`);
2. without ``init``, the global search (:mod:`.search`) scores about a million one-point pose
   hypotheses on the grid and keeps the best distinct ones;
3. those are refined together in the distance field, the best few distinct ones by trimmed
   point-to-plane ICP on the CT's samples (:mod:`.refine`); the one that explains most of the
   target is the answer, the best of the others that sits far enough from it the runner-up, whose
   score gives the confidence.

Everything runs on the CPU in NumPy/SciPy; the same inputs, options and seed give the same pose.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from ..errors import InputError
from ..progress import Progress
from . import rigid
from .constraint import weakest_motion
from .model import BoneModel, prepare_bone
from .options import RegisterOptions, with_overrides
from .refine import icp, refine_in_field
from .result import Registration
from .search import Candidates, distinct, global_search
from .target import prepare_target

MESH_TARGET_SAMPLES = 40_000
"""Area samples drawn from a target given as a mesh (a reconstruction)."""
MIN_TARGET_POINTS = 30
"""Fewest thinned target points a registration accepts."""
_PROBE_POINTS = 256  # CT samples that measure how far apart two poses put the surface


def as_ct_mesh(ct: Any, source: str = "CT") -> trimesh.Trimesh:
    """The CT bone as a mesh: a :class:`trimesh.Trimesh`, a ``(vertices, faces)`` pair or a mesh
    file (mm)."""
    from ..evaluation.sampling import mesh_arrays
    from ..io import check_units, load_mesh

    if isinstance(ct, (str, os.PathLike)):
        source = str(ct)
        mesh = load_mesh(ct)
    else:
        v, f = mesh_arrays(ct, source)
        mesh = ct if isinstance(ct, trimesh.Trimesh) else trimesh.Trimesh(v, f, process=False)
    if len(mesh.faces) == 0:
        raise InputError(f"{source}: holds no triangles")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.isfinite(v).all():
        raise InputError(f"{source}: the mesh has vertices with NaN or Inf")
    check_units(v, source)
    if not mesh.area > 0:
        raise InputError(f"{source}: the mesh has no area")
    return mesh


def as_target_points(target: Any, seed: int = 0, source: str = "target") -> tuple[np.ndarray, str]:
    """The target as points (mm) and what it was (``points`` or ``mesh``): an ``(N, 3)`` array, a
    mesh (its area samples), anything with a ``mesh`` attribute (a
    :class:`~ultraboneudf.Reconstruction`) or a file — a mesh file with triangles is a mesh, any
    other a point cloud."""
    from ..evaluation.sampling import sample_surface
    from ..io import check_units, load_points, validate_points

    if isinstance(target, (str, os.PathLike)):
        path = Path(target)
        source = str(path)
        mesh = mesh_file(path)
        if mesh is None:
            points = load_points(path)
            check_units(points, source)
            return points, "points"
        target = mesh
    if hasattr(target, "mesh") and not isinstance(target, trimesh.Trimesh):
        if target.mesh is None:
            raise InputError(f"{source}: the reconstruction has no mesh")
        target = target.mesh
    if isinstance(target, trimesh.Trimesh):
        if len(target.faces) == 0 or not target.area > 0:
            raise InputError(f"{source}: the mesh holds no triangles with area")
        points = sample_surface(target, MESH_TARGET_SAMPLES, seed=seed, source=source)
        check_units(points, source)
        return points, "mesh"
    points = validate_points(target, source)
    check_units(points, source)
    return points, "points"


def mesh_file(path: Path) -> trimesh.Trimesh | None:
    """The mesh in ``path`` if it is a mesh file holding triangles, else ``None`` (a point cloud, or
    no such file: the point reader says so). :class:`InputError` naming the file when it is
    damaged (:func:`~ultraboneudf.io.read_mesh`)."""
    from ..io import load_mesh, read_mesh

    suffix = path.suffix.lower()
    if suffix in (".stl", ".obj", ".off"):
        return load_mesh(path)
    if suffix != ".ply" or not path.is_file():
        return None
    return read_mesh(path)


def register(ct: Any, target: Any, *, init: np.ndarray | None = None, seed: int = 0,
             options: RegisterOptions | None = None, progress: Progress | None = None, workers: int = -1,
             **overrides: Any) -> Registration:
    """The rigid transform that places the CT bone ``ct`` on the ultrasound ``target``.

    Parameters
    ----------
    ct : the CT bone surface (mm): a :class:`trimesh.Trimesh`, a ``(vertices, faces)`` pair or a
        mesh file. Closed or open.
    target : the ultrasound surface (mm, its own frame): an ``(N, 3)`` point cloud, a mesh (e.g. a
        reconstruction; its area samples are used), a :class:`~ultraboneudf.Reconstruction`, or a
        file of either. It may show only part of the bone, from one side, with false echoes.
    init : optional ``(4, 4)`` CT → target starting pose (e.g.
        :func:`~ultraboneudf.registration.initial.pose_from_landmarks`); without it the pose is
        searched for globally (no initial pose needed).
    seed : seeds every random choice; the same inputs, options and seed give the same pose.
    options, overrides : :class:`RegisterOptions`, and keyword overrides of its fields.
    progress : where to report the stages (default: silent).
    workers : threads of the nearest-neighbour searches (-1: all cores); the pose does not depend on it.

    Returns a :class:`Registration` whose ``transform`` maps CT coordinates to target coordinates.
    """
    start = time.perf_counter()
    progress = progress or Progress(quiet=True)
    opts = with_overrides(options or RegisterOptions(), overrides)
    mesh = as_ct_mesh(ct)
    points, kind = as_target_points(target, seed)
    if init is not None:
        from .initial import check_rigid

        init = check_rigid(init, "init")
    lo, hi = mesh.bounds
    diagonal = float(np.linalg.norm(hi - lo))
    _check_sizes(points, diagonal)
    opts = opts.resolve(diagonal)
    model = prepare_bone(mesh, margin=max(20.0, 1.5 * opts.search_tau_mm), spacing=opts.grid_mm, seed=seed)
    tgt = prepare_target(points, opts.voxel_mm, opts.normal_radius_mm, workers=workers)
    if len(tgt.points) < MIN_TARGET_POINTS:
        raise InputError(f"target: only {len(tgt.points)} points remain one per {opts.voxel_mm:g} mm cell; "
                         f"a registration needs at least {MIN_TARGET_POINTS} (a larger part of the bone)")
    rng = np.random.default_rng(seed)
    probe = model.points[rng.choice(len(model.points), _PROBE_POINTS, replace=False)]
    prepared = time.perf_counter()

    if init is None:
        found = global_search(model, tgt, rng, anchors=opts.anchors, turns=opts.turns,
                              ct_spacing=opts.ct_spacing_mm, tau=opts.search_tau_mm,
                              first_points=opts.first_points, second_points=opts.second_points,
                              keep=opts.keep, progress=progress)
        found = found.take(distinct(rigid.invert(found.transforms), probe, opts.search_tau_mm / 3.0,
                                    opts.candidates))
    else:
        back = rigid.invert(init)
        found = Candidates(back[None, :3, :3], back[None, :3, 3], np.ones(1), hypotheses=0)
    searched = time.perf_counter()

    with progress.stage("refine", total=None) as advance:
        sample = tgt.points[rng.choice(len(tgt.points), min(opts.refine_points, len(tgt.points)), replace=False)]
        last = opts.icp_cutoffs_mm[-1]
        cutoffs = tuple(sorted({max(opts.search_tau_mm, last), max(opts.search_tau_mm / 2.0, last), last},
                               reverse=True))
        refined = refine_in_field(model, found, sample, cutoffs, 24, last)
        advance(1)
        quick = tgt.points[np.sort(rng.choice(len(tgt.points), min(opts.quick_points, len(tgt.points)),
                                               replace=False))]
        finals = _finalists(model, refined, quick, probe, opts, workers, advance)
    best = max(range(len(finals)), key=lambda i: finals[i][0])
    score, pose = finals[best]
    if len(tgt.points) > len(quick):
        full = tgt.points
        if len(full) > opts.icp_points:
            full = full[np.sort(rng.choice(len(full), opts.icp_points, replace=False))]
        pose = icp(model, pose, full, opts.icp_cutoffs_mm[-1:], opts.icp_iterations, workers=workers).transform
    to_target = rigid.invert(pose)
    runner_up = None
    others = [(s, rigid.invert(p)) for i, (s, p) in enumerate(finals) if i != best]
    apart = [(s, p, float(rigid.displacement(p, to_target, probe).mean())) for s, p in others]
    apart = [a for a in apart if a[2] > opts.separation_mm]
    if apart:
        s, p, dist = max(apart, key=lambda a: a[0])
        runner_up = {"transform": p, "score": s, "distance_mm": dist}
    confidence = None
    if init is None:
        confidence = 1.0 if runner_up is None else float(np.clip(1.0 - runner_up["score"] / max(score, 1e-12), 0, 1))

    placed = rigid.apply(pose, tgt.points)
    d = surface_distance(model, placed, workers)
    inliers = d <= opts.inlier_mm
    coverage = _coverage(model, placed, opts.inlier_mm, workers)
    weakest = weakest_motion(model, placed, opts.icp_cutoffs_mm[-1], probe, to_target, workers)
    done = time.perf_counter()
    return Registration(
        transform=to_target,
        residual_mm=float(np.sqrt(np.mean(d[inliers] ** 2))) if inliers.any() else float("nan"),
        overlap=float(inliers.mean()),
        coverage=coverage,
        score=_score(d, opts.inlier_mm),
        confidence=confidence,
        runner_up=runner_up,
        weakest_motion=weakest,
        inlier_mm=opts.inlier_mm,
        hypotheses=int(found.hypotheses),
        timings={"prepare_s": prepared - start, "search_s": searched - prepared, "refine_s": done - searched,
                 "total_s": done - start},
        counts={"target_points": int(len(points)), "target_thinned": int(len(tgt.points)),
                "ct_faces": int(len(mesh.faces)), "ct_samples": int(len(model.points)),
                "candidates": int(len(found)), "finalists": int(len(finals))},
        seed=int(seed),
        options=opts.to_dict(),
        init=None if init is None else {"transform": [[float(v) for v in row] for row in init]},
        input={"target_kind": kind},
    )


def _finalists(model: BoneModel, refined: Candidates, points: np.ndarray, probe: np.ndarray,
               opts: RegisterOptions, workers: int, advance) -> list[tuple[float, np.ndarray]]:
    """ICP (on ``points``) of the refined candidates, best first, skipping any within
    ``separation_mm`` of a pose already taken through ICP, until ``finalists`` are done and one of
    them lies apart from the best (a runner-up), or ``2 × finalists`` are done. Returns
    ``(score, pose target → CT)`` pairs."""
    finals: list[tuple[float, np.ndarray]] = []
    back = rigid.invert(refined.transforms)              # CT → target: displacements of the CT surface
    placed: list[np.ndarray] = []
    for i in range(len(refined)):
        if placed and min(float(rigid.displacement(back[i], p, probe).mean()) for p in placed) <= opts.separation_mm:
            continue
        fit = icp(model, refined.transforms[i], points, opts.icp_cutoffs_mm, opts.icp_iterations, workers=workers)
        finals.append((_score(fit.distances, opts.inlier_mm), fit.transform))
        placed += [back[i], rigid.invert(fit.transform)]
        advance(1)
        if len(finals) >= 2 * opts.finalists:
            break
        if len(finals) >= opts.finalists:
            best = rigid.invert(max(finals, key=lambda f: f[0])[1])
            if any(rigid.displacement(rigid.invert(p), best, probe).mean() > opts.separation_mm for _, p in finals):
                break
    return finals


def _score(d: np.ndarray, tau: float) -> float:
    return float(np.maximum(0.0, 1.0 - (d / tau) ** 2).mean())


def surface_distance(model: BoneModel, points: np.ndarray, workers: int = -1) -> np.ndarray:
    """Distance (mm) ``(N,)`` from ``points`` (CT frame) to the CT surface: to the tangent plane of
    the nearest sample where the point lies over it (within the samples' spacing sideways), else to
    the sample itself."""
    d, idx = model.tree.query(points, workers=workers)
    normal = np.einsum("ij,ij->i", points - model.points[idx], model.normals[idx])
    sideways = np.sqrt(np.maximum(d ** 2 - normal ** 2, 0.0))
    spacing = np.sqrt(model.area / len(model.points))
    return np.where(sideways <= spacing, np.abs(normal), d)


def _coverage(model: BoneModel, placed: np.ndarray, tau: float, workers: int = -1) -> float:
    """Share of the CT's samples within ``tau`` mm of a placed target point."""
    from ..geometry.neighbors import kd_tree

    return float((kd_tree(placed).query(model.points, workers=workers)[0] <= tau).mean())


def _check_sizes(points: np.ndarray, diagonal: float) -> None:
    """Refuse a target far larger than the CT bone (mixed units, or the wrong files)."""
    lo, hi = np.percentile(points, [5, 95], axis=0)
    extent = float(np.linalg.norm(hi - lo))
    if extent > 3.0 * diagonal:
        raise InputError(f"target: its points span {extent:.0f} mm (5th–95th percentile), the CT bone only "
                         f"{diagonal:.0f} mm: are both in mm, and is this the CT of the scanned bone?")
