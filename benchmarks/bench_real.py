"""Real ultrasound against CT: every method on real compounded clouds and on a real tracked sweep.

Inputs (paths given on the command line, mm, each in the frame of its CT):

* ``--cloud NAME=POINTS,CT`` (repeatable), or ``--clouds DIR`` for every ``*_us.npy`` beside its
  ``*_ct.stl``: a compounded ultrasound cloud (any file ``reconstruct`` reads) and the CT bone mesh.
  UltraBonesHip's seven early-access clouds (five femurs and two pelves of three cadavers; Wu et
  al., luohwu/NeuralBoneReg-implementation at commit 57d07b0, docs/real_data.md) are laid out so.
  ``--points N`` runs each as a random subset of N of its points (case ``NAME/Npts``): a sparser
  cloud of the same bone, as a user whose compounding kept fewer points has; ``--cloud-frame-step
  K`` as every K-th of its frames (``frames_from_order``; case ``NAME/every_K``): a sweep with fewer
  frames.
* ``--sweep DIR --ct MESH``: a tracked sweep and the CT of one bone it images, e.g. the whole sweep of
  the public UltraBones100k repository (``CT-US bone alignment optimization/record_folder``: its
  ``UltrasoundImages`` as ``frames/``, ``sweep_initial.csv`` as ``poses.csv`` and the calibration of
  the sample, ``docs/sweep.md``) with ``CT_models/Fibula.stl``. ``--frame-steps 1,3,10`` takes every
  k-th frame. Each step's points come from the front end (``ultraboneudf.sweep_points``:
  segmentation, compounding, the front end's filters, frame registration), cached under
  ``--cache``, and are reconstructed twice: with each point's probe position and frame (``sweep``:
  what ``reconstruct SWEEP`` does) and without (``cloud``: what a user with only the cloud gets).

Scores, as the paper scores real data (every distance over ``--samples`` area samples of each mesh):
pseudo ground truth (pGT) = the CT surface within 2 mm of an input point; ``cd_mm`` = ½(mean mesh →
pGT + mean pGT → mesh); ``hd95_mm`` = the larger directed 95th percentile; ``on_bone`` = share of the
mesh area within 2 mm of the CT; ``covered`` = share of the pGT within 2 mm of the mesh; ``pieces`` =
the mesh's parts connected across edges; ``off_mm2`` = mesh area more than 2 mm from the CT. On the sweep the
CT is one of the bones in view (the fibula beside the tibia): CD, HD95 and ``on_bone`` score the
mesh within ``--near-mm`` (10 mm) of it, and ``far_mm2`` is the area beyond (the other bones, and
anything invented there). The row ``points`` scores the input points themselves as if they were the
surface. ``time_s`` is end to end.

``--register`` scores every mesh a second time (``reg_cd_mm``, ``reg_hd95_mm``, ``reg_on_bone``,
``reg_covered``) against the CT moved onto the input points by ``ultraboneudf.register`` (rigid,
started from the CT's own pose; ``reg_turn_deg`` and ``reg_shift_mm`` on the ``points`` row: its
rotation and the mean distance it moves the CT's vertices). That motion takes out what moves the
whole cloud against its CT (an error of the data's CT registration, and an offset of the segmented
band seen mostly from one side), which no reconstruction from the points can: what is left is the
reconstruction's.

``--pose principal`` runs every input (points, probe positions and CT together) turned into the
cloud's principal axes about its centroid (the axes signed by the points' skew, right-handed): the
same data in another frame, so the scores move only with what depends on the frame (grids,
lattices, the column rule's representatives). Rows carry ``pose``; compare them with ``given``.

The input points are described against the CT too (``--describe``, also printed with every run):
their distance to the bone in bands, and the groups that the points more than 2 mm off it form
(linked across 2 mm gaps): how many, how large, their shape (``line``, ``sheet``, ``blob`` by the
spread of their principal axes) and their side (in front of the bone, outside the CT, or behind it);
and, for the points within 5 mm of the bone, their median signed distance to it by the angle between
the beam and the bone's normal (``by_incidence``, 15° bins): how far out of the bone an oblique face's
echoes lie. A sweep's beams are known; a compounded cloud written frame by frame, each frame row
by row (as the UltraBonesHip clouds are), tells its frames' beams by that order
(``beams_from_order``; ``beams``: ``order``); one that keeps only its frames' points together has
its beams estimated, each frame's as the second principal axis of its points within its plane (on
the fibula sweep, where the true beams are known, a median 16° off them; ``frames``); a cloud in
another order has no such row.

    python benchmarks/bench_real.py --clouds REAL_CLOUDS_DIR --methods ultraboneudf,ultraboneudf@fast,poisson
    python benchmarks/bench_real.py --sweep SWEEP_DIR --ct Fibula.stl --frame-steps 3,10
    python benchmarks/bench_real.py --clouds DIR --json bench_out/real.jsonl --pictures bench_out/real_png
    python benchmarks/bench_real.py --clouds DIR --describe
    python benchmarks/bench_real.py --clouds DIR --methods ultraboneudf --pose principal

Rows are appended to ``--json`` as they finish and a rerun skips those already there (same case,
method, preset, seed, iterations, ``--set`` and pose).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

METHODS = "ultraboneudf,poisson,capudf,funsr,carotidudf,vanilla_udf,ultraboneudf_pull"
PSEUDO_GT_MM = 2.0
ON_BONE_MM = 2.0
CT_SAMPLES = 2_000_000
GROUP_LINK_MM = 2.0
COLUMNS = ["case", "variant", "method", "preset", "cd_mm", "hd95_mm", "on_bone", "covered", "pieces", "off_mm2",
           "far_mm2", "time_s"]


class Truth:
    """A CT bone mesh prepared for scoring one input: dense samples with their outward normals, and
    the pseudo ground truth of the input points."""

    def __init__(self, ct, points: np.ndarray, samples: int = CT_SAMPLES):
        """``ct``: the CT mesh's file, or the mesh itself (mm, in the points' frame)."""
        import trimesh

        from ultraboneudf import load_mesh
        from ultraboneudf.evaluation.sampling import sample_surface
        from ultraboneudf.geometry.neighbors import kd_tree

        self.mesh = ct if isinstance(ct, trimesh.Trimesh) else load_mesh(ct)
        self.samples = sample_surface(self.mesh, samples, seed=1)
        self.tree = kd_tree(self.samples)
        self._vertices = kd_tree(np.asarray(self.mesh.vertices))
        d = kd_tree(points).query(self.samples, k=1, distance_upper_bound=PSEUDO_GT_MM * 1.0001,
                                  workers=-1)[0]
        self.pgt = self.samples[d <= PSEUDO_GT_MM]
        self.pgt_tree = kd_tree(self.pgt)

    def signed(self, points: np.ndarray, with_normals: bool = False):
        """Distance (N,) of each point to the CT surface, positive outside the bone (in front of it;
        the side from the nearest vertex's normal); with ``with_normals`` also that normal (N, 3)."""
        d = self.tree.query(points, k=1, workers=-1)[0]
        _, v = self._vertices.query(points, k=1, workers=-1)
        normals = self.mesh.vertex_normals[v]
        side = np.einsum("ij,ij->i", points - self.mesh.vertices[v], normals)
        signed = np.where(side < 0, -d, d)
        return (signed, normals) if with_normals else signed

    def score(self, surface: np.ndarray, area: float | None = None, near: float | None = None) -> dict:
        """The scores of the module docstring for area samples (or points) ``surface`` of a mesh of
        ``area`` mm² (``None`` for points). With ``near`` (mm), the CT's bone is one of several in
        view: CD, HD95 and ``on_bone`` score the samples within ``near`` of it, and ``far_mm2`` is
        the area beyond (the other bones, and anything invented there)."""
        from ultraboneudf.geometry.neighbors import kd_tree

        to_bone = self.tree.query(surface, k=1, workers=-1)[0]
        own = np.ones(len(surface), dtype=bool) if near is None else to_bone <= near
        d_rg = self.pgt_tree.query(surface[own], k=1, workers=-1)[0]
        d_gr = kd_tree(surface).query(self.pgt, k=1, workers=-1)[0]
        off = to_bone > ON_BONE_MM
        out = {"cd_mm": round(0.5 * float(d_rg.mean() + d_gr.mean()), 3),
               "hd95_mm": round(max(float(np.percentile(d_rg, 95)), float(np.percentile(d_gr, 95))), 2),
               "on_bone": round(1.0 - float(off[own].mean()), 3), "covered": round(float(np.mean(d_gr <= 2.0)), 3),
               "off_mm2": None if area is None else round(float(area * off.mean()), 1)}
        if near is not None and area is not None:
            out["far_mm2"] = round(float(area * np.mean(~own)), 1)
        return out


def frame_beams(points: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(N, 3) each point's beam as estimated from its frame (``label`` from
    :func:`~ultraboneudf.geometry.frame_order.frames_from_order`):
    the second principal axis of the frame's points, within its plane across the bone's curve; zero
    rows for points in no frame. Unsigned."""
    beams = np.zeros((len(points), 3))
    for f in np.unique(label[label >= 0]):
        rows = np.flatnonzero(label == f)
        q = points[rows]
        beams[rows] = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)[2][1]
    return beams


def by_incidence(signed: np.ndarray, normals: np.ndarray, beams: np.ndarray) -> dict:
    """The points within 5 mm of the bone, binned by the angle between their beam (N, 3, unsigned;
    zero rows skipped) and the bone's normal at their nearest point (N, 3): per 15° bin, how many
    and their median signed distance (mm, positive out of the bone)."""
    has = np.any(beams != 0, axis=1) & (np.abs(signed) <= 5.0)
    cos = np.abs(np.einsum("ij,ij->i", normals[has], beams[has])) / np.linalg.norm(beams[has], axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    out = {}
    for lo in range(0, 90, 15):
        m = (angle >= lo) & (angle < lo + 15)
        if m.any():
            out[f"{lo}-{lo + 15}"] = {"points": int(m.sum()), "median_mm": round(float(np.median(signed[has][m])), 2)}
    return out


def describe(points: np.ndarray, truth: Truth, probe: np.ndarray | None = None) -> dict:
    """The input points against the CT: distance bands, the off-bone groups and the offset by the
    beam's incidence (module docstring); ``probe`` (N, 3): each point's scan-line origin, if known."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from ultraboneudf.geometry.neighbors import kd_tree

    s, normals = truth.signed(points, with_normals=True)
    d = np.abs(s)
    out = {"points": len(points), "median_mm": round(float(np.median(d)), 2),
           "band": {k: round(float(np.mean(m)), 3) for k, m in
                    (("<=2", d <= 2), ("2-5", (d > 2) & (d <= 5)), ("5-15", (d > 5) & (d <= 15)), (">15", d > 15))},
           "max_mm": round(float(d.max()), 1), "off_in_front": round(float(np.mean(s[d > 2] > 0)), 3) if (d > 2).any() else None}
    off = np.flatnonzero(d > 2)
    if len(off) > 1:
        pairs = kd_tree(points[off]).query_pairs(GROUP_LINK_MM, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(off), len(off)))
        _, label = connected_components(graph, directed=False)
        size = np.bincount(label)
        shapes = {"line": 0, "sheet": 0, "blob": 0, "single": 0}
        in_shape = dict.fromkeys(shapes, 0)
        for g in np.flatnonzero(size >= 1):
            rows = off[label == g]
            kind = "single" if len(rows) < 5 else _shape(points[rows])
            shapes[kind] += 1
            in_shape[kind] += len(rows)
        out["off_groups"] = {"count": int(len(size)), "size_median": float(np.median(size)),
                             "size_max": int(size.max()), "by_shape": shapes,
                             "points_by_shape": {k: round(v / len(off), 3) for k, v in in_shape.items()}}
    if probe is not None:
        out["beams"], beams = "probe", points - probe
    else:
        from ultraboneudf.geometry.frame_order import beams_from_order, frames_from_order

        label = frames_from_order(points)
        told = beams_from_order(points, label)
        in_order = np.mean(label >= 0) >= 0.5  # a cloud that keeps its frames' points together
        if told.any():  # written row by row: each frame's own beam (rows it does not tell skipped)
            out["beams"], beams = "order", told
        else:
            out["beams"], beams = ("frames", frame_beams(points, label)) if in_order else (None, None)
    if beams is not None:
        out["by_incidence"] = by_incidence(s, normals, beams)
    return out


def _shape(p: np.ndarray) -> str:
    """``line``, ``sheet`` or ``blob`` by the principal spreads of the points ``p``."""
    lam = np.sort(np.linalg.eigvalsh(np.cov(p.T)))[::-1]
    if lam[1] < 0.1 * lam[0]:
        return "line"
    return "sheet" if lam[2] < 0.1 * lam[1] else "blob"


def clouds_from(args: argparse.Namespace) -> list[tuple[str, Path, Path]]:
    """(name, points file, CT mesh) of every cloud named on the command line."""
    out = []
    for item in args.cloud:
        name, _, paths = item.partition("=")
        pts, _, ct = paths.partition(",")
        if not (name and pts and ct):
            sys.exit(f"--cloud {item!r}: expected NAME=POINTS,CT")
        out.append((name, Path(pts), Path(ct)))
    if args.clouds:
        for us in sorted(args.clouds.glob("*_us.npy")):
            ct = us.with_name(us.name[: -len("_us.npy")] + "_ct.stl")
            if ct.exists():
                out.append((us.name[: -len("_us.npy")], us, ct))
    return out


def sparser(points: np.ndarray, n: int) -> np.ndarray:
    """``n`` of ``points`` (N, 3), drawn at random without replacement (always the same draw), in
    their order (a compounded cloud's frames stay runs); all of them when ``n`` ≥ N."""
    if n >= len(points):
        return points
    return points[np.sort(np.random.default_rng(0).choice(len(points), n, replace=False))]


def every_kth_frame(points: np.ndarray, k: int) -> np.ndarray:
    """The points of every ``k``-th frame of a compounded cloud that keeps each frame's points
    together (:func:`~ultraboneudf.geometry.frame_order.frames_from_order`), in their order; the
    points in no frame are left out."""
    from ultraboneudf.geometry.frame_order import frames_from_order

    label = frames_from_order(points)
    return points[(label >= 0) & (label % k == 0)]


def principal_pose(points: np.ndarray) -> np.ndarray:
    """The 4 × 4 rigid motion (mm) taking ``points`` (N, 3) into their principal axes: the centroid to
    the origin, the axes by decreasing spread, the first two signed so that the points' skew along
    them is positive and the third so that the frame stays right-handed. The same cloud turned
    and moved gets the same image, but for axes of equal spread or no skew."""
    centre = points.mean(axis=0)
    q = points - centre
    _, axes = np.linalg.eigh(q.T @ q)
    axes = axes[:, ::-1].copy()
    for k in range(2):
        if np.mean((q @ axes[:, k]) ** 3) < 0:
            axes[:, k] *= -1.0
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1.0
    motion = np.eye(4)
    motion[:3, :3] = axes.T
    motion[:3, 3] = -axes.T @ centre
    return motion


def sweep_cloud(sweep: Path, step: int, cache: Path, seed_log) -> Path:
    """The sweep's points at every ``step``-th frame (the front end,
    :func:`ultraboneudf.sweep_points`, with its defaults), cached as PLY with each point's probe
    position and frame, as ``sweep2points`` writes them."""
    out = cache / f"{sweep.name}_step{step}.ply"
    if not out.exists():
        from ultraboneudf import SweepOptions, sweep_points
        from ultraboneudf.io import atomic_write_bytes, encode_points

        cache.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        atomic_write_bytes(out, encode_points(out, sweep_points(sweep, SweepOptions(frame_step=step)).cloud))
        seed_log(f"sweep points every {step}th frame: {time.perf_counter() - t0:.0f} s")
    return out


def run(method: str, preset: str, points: np.ndarray, truth: Truth, args: argparse.Namespace, probe=None,
        frames=None, near: float | None = None, registered: Truth | None = None):
    """One reconstruction and its scores (``near``: :meth:`Truth.score`; ``registered``:
    :func:`mesh_scores`); returns the row and the mesh (``None`` on failure)."""
    import ultraboneudf
    from ultraboneudf.errors import InputError

    overrides = {"train.iters": args.iters} if args.iters and method != "poisson" else {}
    t0 = time.perf_counter()
    try:
        rec = ultraboneudf.reconstruct(points, preset=preset, device=args.device, seed=args.seed, method=method,
                                       assignments=args.set, probe_positions=probe, frame_index=frames,
                                       **overrides)
    except InputError as exc:  # e.g. the Poisson extra is not installed
        return {"error": str(exc)}, None
    row = {"time_s": round(time.perf_counter() - t0, 1), "points": len(points)}
    if rec.mesh is None:
        return {**row, "failed": True}, None
    row.update(mesh_scores(truth, rec.mesh, args.samples, near, registered))
    return row, rec.mesh


def mesh_scores(truth: Truth, mesh, samples: int, near: float | None, registered: Truth | None = None) -> dict:
    """:meth:`Truth.score` of ``mesh`` over ``samples`` area samples, and its ``pieces``: the parts
    connected across edges (floating sheets of false echoes each count); with ``registered`` (the CT
    registered to the points, ``--register``), also its ``reg_`` scores."""
    from ultraboneudf.evaluation.sampling import sample_surface

    surface = sample_surface(mesh, samples, seed=0)
    out = truth.score(surface, float(mesh.area), near)
    out["pieces"] = len(mesh.split(only_watertight=False))
    if registered is not None:
        out.update(registered_scores(registered.score(surface, float(mesh.area), near)))
    return out


REGISTERED = ("cd_mm", "hd95_mm", "on_bone", "covered")


def registered_scores(score: dict) -> dict:
    """The scores against the registered CT that the rows carry, ``reg_``-prefixed."""
    return {f"reg_{k}": score[k] for k in REGISTERED}


def registered_truth(mesh, points: np.ndarray, seed: int) -> tuple[Truth, dict]:
    """The CT ``mesh`` (mm, e.g. :attr:`Truth.mesh`) moved onto ``points`` by
    :func:`ultraboneudf.register` (rigid, started from the CT's own pose), and the motion: its
    rotation (degrees) and the mean distance (mm) it moves the CT's vertices."""
    from ultraboneudf import register
    from ultraboneudf.registration.rigid import rotation_angle_deg

    reg = register(mesh, points, init=np.eye(4), seed=seed)
    placed = reg.place(mesh)
    motion = {"reg_turn_deg": round(float(rotation_angle_deg(reg.transform[:3, :3])), 2),
              "reg_shift_mm": round(float(np.linalg.norm(placed.vertices - mesh.vertices, axis=1).mean()), 2)}
    return Truth(placed, points), motion


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cloud", action="append", default=[], metavar="NAME=POINTS,CT")
    p.add_argument("--clouds", type=Path, help="a folder of *_us.npy clouds with their *_ct.stl")
    p.add_argument("--sweep", type=Path, help="a tracked sweep (folder or sequence file)")
    p.add_argument("--ct", type=Path, help="the CT bone mesh of --sweep")
    p.add_argument("--frame-steps", default="1,3,10")
    p.add_argument("--near-mm", type=float, default=10.0, help="--sweep: score the mesh within this of the CT's "
                   "bone; the area beyond is reported as far_mm2 (other bones in view)")
    p.add_argument("--methods", default=METHODS, help="comma-separated; METHOD@PRESET runs a method with "
                   "another preset than --preset (e.g. ultraboneudf@fast)")
    p.add_argument("--preset", default="robust")
    p.add_argument("--iters", type=int, default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=300_000, help="area samples per mesh")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--describe", action="store_true", help="only describe the inputs against their CT")
    p.add_argument("--pose", choices=("given", "principal"), default="given", help="run every input in its "
                   "own frame, or turned with its CT into the cloud's principal axes")
    p.add_argument("--points", type=int, default=None, metavar="N", help="run each compounded cloud as a "
                   "random subset of N of its points (seeded; the case is named NAME/Npts): sparser clouds")
    p.add_argument("--cloud-frame-step", type=int, default=None, metavar="K", help="run each compounded "
                   "cloud as every K-th of its frames (found from the points' order; case NAME/every_K)")
    p.add_argument("--register", action="store_true", help="also score against the CT registered to each "
                   "input's points (reg_ columns)")
    p.add_argument("--rescore", action="store_true", help="score the rows already in --json again from their "
                   "meshes in --meshes (after a change of the scoring), rewriting --json")
    p.add_argument("--cache", type=Path, default=Path("bench_out/real_inputs"))
    p.add_argument("--json", type=Path, help="append each row here (JSON lines); skip rows already in it")
    p.add_argument("--pictures", type=Path, help="one distance-coloured PNG per input here")
    p.add_argument("--meshes", type=Path, help="write each mesh here (CASE_VARIANT_METHOD_PRESET.ply, mm); a "
                   "row already in --json takes its mesh from here for the pictures")
    args = p.parse_args()
    import torch

    from ultraboneudf import load_points
    from ultraboneudf.io import load_sweep_columns

    if args.threads:
        torch.set_num_threads(args.threads)
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    inputs = []  # (case, variant, points, probe, frames, ct, near)
    for name, pts, ct in clouds_from(args):
        points = load_points(pts)
        if args.points:
            name, points = f"{name}/{args.points}pts", sparser(points, args.points)
        if args.cloud_frame_step:
            name, points = f"{name}/every_{args.cloud_frame_step}", every_kth_frame(points, args.cloud_frame_step)
        inputs.append((name, "cloud", points, None, None, ct, None))
    if args.sweep:
        if not args.ct:
            sys.exit("--sweep needs --ct (the CT mesh of the bone to score)")
        for step in (int(s) for s in args.frame_steps.split(",")):
            path = sweep_cloud(args.sweep, step, args.cache, log)
            points = load_points(path)
            probe, frames = load_sweep_columns(path, len(points))
            case = f"{args.sweep.name}/{step}"
            inputs.append((case, "sweep", points, probe, frames, args.ct, args.near_mm))
            inputs.append((case, "cloud", points, None, None, args.ct, args.near_mm))
    if not inputs:
        sys.exit("nothing to run: give --cloud, --clouds or --sweep with --ct")
    done = []
    if args.json and args.json.exists():
        done = [json.loads(line) for line in args.json.read_text().splitlines() if line.strip()]
    rows, truths, registered, rescored = [], {}, {}, False
    for case, variant, points, probe, frames, ct, near in inputs:
        if args.pose == "principal":
            from trimesh.transformations import transform_points

            turn = principal_pose(points)
            points = transform_points(points, turn)
            probe = None if probe is None else transform_points(probe, turn)
        if case not in truths:
            if args.pose == "principal":
                from ultraboneudf import load_mesh

                ct = load_mesh(ct).apply_transform(turn)
            truths[case] = Truth(ct, points)
            info = describe(points, truths[case], probe)
            log(f"{case}: {json.dumps(info)}")
            score = truths[case].score(points, near=near)
            rows.append({"case": case, "variant": "input", "method": "points", **score,
                         "points": len(points), "pose": args.pose, "describe": info})
            if args.register:
                registered[case], motion = registered_truth(truths[case].mesh, points, args.seed)
                rows[-1].update(motion, **registered_scores(registered[case].score(points, near=near)))
        if args.describe:
            continue
        truth, meshes = truths[case], {}
        for method in args.methods.split(","):
            name, _, preset = method.partition("@")
            preset = preset or args.preset
            key = {"case": case, "variant": variant, "method": name, "preset": preset, "seed": args.seed,
                   "iters_override": args.iters, "set": args.set, "pose": args.pose}
            old = next((r for r in done if all(r.get(k, "given" if k == "pose" else None) == v
                                               for k, v in key.items())), None)
            stored = None if args.meshes is None else args.meshes / mesh_name(case, variant, name, preset, args.pose)
            if old is not None:
                if stored is not None and stored.exists():  # for the pictures, or to score again
                    from ultraboneudf import load_mesh

                    meshes[method] = load_mesh(stored)
                    if args.rescore:
                        old.update(mesh_scores(truth, meshes[method], args.samples, near, registered.get(case)))
                        rescored = True
                rows.append(old)
                continue
            row, mesh = run(name, preset, points, truth, args, probe, frames, near, registered.get(case))
            rows.append({**key, **row})
            log(json.dumps(rows[-1]))
            if args.json:
                args.json.parent.mkdir(parents=True, exist_ok=True)
                with args.json.open("a") as f:
                    f.write(json.dumps(rows[-1]) + "\n")
            meshes[method] = mesh
            if stored is not None and mesh is not None:
                args.meshes.mkdir(parents=True, exist_ok=True)
                mesh.export(stored)
        if args.pictures and meshes:
            from ultraboneudf.evaluation.render import render_grid_png

            args.pictures.mkdir(parents=True, exist_ok=True)
            meshes = {"input points": points_as_mesh(points), **meshes}
            suffix = "" if args.pose == "given" else f"_{args.pose}"
            render_grid_png(args.pictures / f"{case.replace('/', '_')}_{variant}{suffix}.png", meshes,
                            truth.samples[:: max(1, len(truth.samples) // 300_000)], views=("front", "right", "top"),
                            ground_truth=truth.mesh)
    if rescored:  # the file again, every row as scored now
        kept = [r for r in done if not any(r is row for row in rows)]
        text = "".join(json.dumps(r) + "\n" for r in kept + [r for r in rows if r.get("variant") != "input"])
        from ultraboneudf.io import atomic_write_bytes

        atomic_write_bytes(args.json, text.encode())
    print_table(rows)


def points_as_mesh(points: np.ndarray, size: float = 0.6):
    """The points drawn as small triangles (``size`` mm), so that the mesh renderer shows a cloud."""
    import trimesh

    # in the plane normal to (1, 1, 1): seen edge-on from no axis-aligned view
    corner = size * np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, -2.0]]) / [[1.0], [2 ** 0.5], [6 ** 0.5]]
    vertices = (points[:, None, :] + corner[None]).reshape(-1, 3)
    return trimesh.Trimesh(vertices, np.arange(len(vertices)).reshape(-1, 3), process=False)


def mesh_name(case: str, variant: str, method: str, preset: str, pose: str = "given") -> str:
    """The file name of a row's mesh under ``--meshes`` (a ``principal`` pose's mesh lies in that frame)."""
    suffix = "" if pose == "given" else f"_{pose}"
    return f"{case.replace('/', '_')}_{variant}_{method}_{preset}{suffix}.ply"


def print_table(rows: list[dict]) -> None:
    extra = [f"reg_{k}" for k in REGISTERED] + ["reg_turn_deg", "reg_shift_mm"]
    columns = COLUMNS + [c for c in extra if any(c in r for r in rows)]
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))
    for r in rows:
        cells = ["" if r.get(c) is None else str(r.get(c)) for c in columns]
        if r.get("failed"):
            cells[4] = "no surface"
        if r.get("error"):
            cells[4] = f"not run: {r['error']}"
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
