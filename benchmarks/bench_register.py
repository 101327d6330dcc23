"""CT → ultrasound registration from random starts, against known poses.

Every case is an ultrasound surface already in its CT's frame, so the true pose is the identity.
The CT is moved by ``--starts`` random rigid motions (seeded per case: a rotation of up to
``--max-deg`` about a uniformly random axis through the CT's centre, then a translation of up to
``--max-mm`` in a uniformly random direction) and registered back with ``ultraboneudf.register``
(no initial pose). Errors, in the target frame:

* ``mean_mm`` / ``max_mm``: mean and largest displacement of 20,000 area samples of the CT surface
  between the found and the true pose; a start succeeds when ``mean_mm`` ≤ 2 mm;
* ``rot_deg``: the angle of the rotation between the two poses; ``trans_mm``: how far apart they put
  the CT's centre;
* ``time_s``: one registration, end to end (the CT's grid included).

Cases (each needs its data given by path; those without it are skipped):

* ``femur_us``, ``pelvis_us``: the real clouds with their CT (``--real DIR``, the folder holding
  ``specimen00_left_femur_us.npy``, ``specimen00_left_femur_ct.stl``, ``specimen00_pelvis_…``);
* ``fibula_us``: a real sweep's cloud (``--fibula-cloud``, e.g. written by ``ultraboneudf
  sweep2points``) and its CT (``--fibula-ct``);
* ``sim_femur``, ``sim_pelvis``, ``sim_talus``, ``sim_tibia``: the simulator's ``hard`` sweeps of the
  bone models in ``--bones DIR`` (as ``benchmarks/bench_robust.py`` makes them; the CT is the
  whole bone model).

Targets (``--targets``): ``raw`` (the points as given) and ``mesh`` (the default preset's
reconstruction of them, seed 0, made once and kept in ``--cache``). ``--floor`` adds one row per
case: the refinement alone started at the true pose (``init``), i.e. the pose the ultrasound itself
pulls to, which bounds what any search can reach. ``--icp-only`` adds the refinement alone from each
random start (``init`` = the moved CT where it lies), what local registration without a search gives.

    python benchmarks/bench_register.py --real ../shared/data/real_clouds --cases femur_us,pelvis_us
    python benchmarks/bench_register.py --bones ../shared/data/bones --cache ../data/reg_cache \\
        --cases sim_femur,sim_pelvis,sim_talus,sim_tibia --targets raw,mesh
    python benchmarks/bench_register.py --fibula-cloud fibula.ply --fibula-ct Fibula.stl --cases fibula_us

``--threads N`` limits NumPy's and the KD-tree's threads (set before NumPy loads). ``--json``
appends one row per registration (JSON lines); ``--pictures DIR`` draws each case's first
registration (``register_CASE_TARGET.png``: the CT in place, coloured by distance to the
ultrasound).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import zlib
from pathlib import Path

CASES = "femur_us,pelvis_us,fibula_us,sim_femur,sim_pelvis,sim_talus,sim_tibia"
SUCCESS_MM = 2.0
SURFACE_SAMPLES = 20_000


def random_motion(rng, centre, max_deg: float, max_mm: float):
    """A rigid 4×4: a turn of up to ``max_deg`` about a random axis through ``centre``, then a
    shift of up to ``max_mm`` in a random direction (angles and lengths uniform)."""
    import numpy as np

    from ultraboneudf.registration import rigid

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    r = rigid.axis_angle(axis, np.radians(rng.uniform(0.0, max_deg)))
    return rigid.homogeneous(r, centre - r @ centre + direction * rng.uniform(0.0, max_mm))


def load_case(name: str, args: argparse.Namespace):
    """(CT mesh, target points (N, 3) mm, probe positions or None, frame indices or None) in the
    CT's frame, or ``None`` when the case's data were not given."""
    from ultraboneudf import load_mesh, load_points

    if name in ("femur_us", "pelvis_us"):
        if not args.real:
            return None
        import numpy as np

        stem = {"femur_us": "specimen00_left_femur", "pelvis_us": "specimen00_pelvis"}[name]
        return load_mesh(args.real / f"{stem}_ct.stl"), np.load(args.real / f"{stem}_us.npy"), None, None
    if name == "fibula_us":
        if not (args.fibula_cloud and args.fibula_ct):
            return None
        from ultraboneudf.io import load_sweep_columns

        points = load_points(args.fibula_cloud)
        probe, frames = load_sweep_columns(args.fibula_cloud, len(points))
        return load_mesh(args.fibula_ct), points, probe, frames
    if name.startswith("sim_"):
        if not (args.bones and args.cache):
            return None
        os.environ["ULTRABONEUDF_BONES"] = str(args.bones)
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_robust import make_input

        bone = name[4:]
        points, probe, _, frames = make_input(bone, "hard", 0, args.cache / "sim")
        return load_mesh(args.bones / f"{bone}.ply"), points, probe, frames
    raise SystemExit(f"unknown case {name!r}; choose from {CASES}")


def reconstructed(name: str, points, probe, frames, args: argparse.Namespace):
    """The default preset's mesh of the case's points (seed 0), made once and kept in --cache."""
    import ultraboneudf
    from ultraboneudf import load_mesh

    path = args.cache / "meshes" / f"{name}_default_seed0.ply"
    if not path.exists():
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        print(f"[{name}] reconstructing (default preset, seed 0) …", file=sys.stderr)
        rec = ultraboneudf.reconstruct(points, seed=0, probe_positions=probe, frame_index=frames)
        if rec.mesh is None:
            raise SystemExit(f"{name}: the reconstruction found no surface")
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(path)
    return load_mesh(path)


def run_case(name: str, args: argparse.Namespace) -> list[dict]:
    import numpy as np

    import ultraboneudf
    from ultraboneudf.evaluation.sampling import sample_surface
    from ultraboneudf.registration import rigid

    loaded = load_case(name, args)
    if loaded is None:
        print(f"[{name}] skipped: its data were not given", file=sys.stderr)
        return []
    ct, points, probe, frames = loaded
    surface = sample_surface(ct, SURFACE_SAMPLES, seed=0)
    centre = surface.mean(axis=0)
    rows = []
    targets = {"raw": points}
    if "mesh" in args.targets:
        targets["mesh"] = reconstructed(name, points, probe, frames, args)
    rng = np.random.default_rng([args.seed, zlib.crc32(name.encode())])
    motions = [random_motion(rng, centre, args.max_deg, args.max_mm) for _ in range(args.starts)]
    opts = dict(kv.split("=", 1) for kv in args.set)
    plan = [(kind, k, m) for kind in args.targets for k, m in enumerate(motions)]
    if args.icp_only:
        plan += [("icp-only", k, m) for k, m in enumerate(motions)]
    if args.floor:
        plan.append(("floor", "floor", np.eye(4)))
    targets["icp-only"] = targets["floor"] = points
    for kind, k, motion in plan:
        moved = ct.copy()
        moved.apply_transform(motion)
        truth = rigid.invert(motion)  # the moved CT → the target (= the CT's own) frame
        start = time.perf_counter()
        init = {"floor": truth, "icp-only": np.eye(4)}.get(kind)
        reg = ultraboneudf.register(moved, targets[kind], seed=0 if k == "floor" else k, workers=args.workers,
                                    init=init, **opts)
        elapsed = time.perf_counter() - start
        on_moved = rigid.apply(motion, surface)
        err = rigid.displacement(reg.transform, truth, on_moved)
        relative = reg.transform[:3, :3] @ truth[:3, :3].T
        row = {"case": name, "target": kind, "start": k, "mean_mm": float(err.mean()), "max_mm": float(err.max()),
               "rot_deg": float(rigid.rotation_angle_deg(relative)),
               "trans_mm": float(np.linalg.norm(rigid.apply(reg.transform, rigid.apply(motion, centre[None]))[0]
                                                - centre)),
               "time_s": elapsed, "confidence": reg.confidence, "overlap": reg.overlap,
               "coverage": reg.coverage, "residual_mm": reg.residual_mm,
               "start_deg": float(rigid.rotation_angle_deg(motion[:3, :3])),
               "sensitivity": reg.weakest_motion["sensitivity"],
               "runner_up_mm": None if reg.runner_up is None else reg.runner_up["distance_mm"]}
        rows.append(row)
        if args.pictures and k == 0:
            from ultraboneudf.io import atomic_write_bytes
            from ultraboneudf.registration.figures import registration_png
            from ultraboneudf.registration.solve import as_target_points

            shown = as_target_points(targets[kind], 0)[0]
            atomic_write_bytes(args.pictures / f"register_{name}_{kind}.png", registration_png(moved, reg, shown))
        if args.json:
            import json

            with open(args.json, "a") as fh:
                fh.write(json.dumps(row) + "\n")
        if args.verbose:
            print(f"[{name}/{kind} {k}] mean {row['mean_mm']:.2f} max {row['max_mm']:.2f} mm, "
                  f"rot {row['rot_deg']:.2f}°, {elapsed:.1f} s, confidence {reg.confidence}", file=sys.stderr)
    return rows


def print_table(rows: list[dict]) -> None:
    import numpy as np

    head = (f"{'case':<11} {'target':<8} {'starts':>6} {'success':>8} {'median':>7} {'p90':>7} {'worst':>7} "
            f"{'max med':>8} {'rot med':>8} {'trans med':>9} {'time med':>9} {'time max':>9} "
            f"{'overlap':>8} {'coverage':>8} {'conf med':>8} {'sens med':>8}")
    print(head)
    print("-" * len(head))
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["case"], r["target"]), []).append(r)
    for (case, target), g in groups.items():
        m = np.array([r["mean_mm"] for r in g])
        conf = [r["confidence"] for r in g if r["confidence"] is not None]
        print(f"{case:<11} {target:<8} {len(g):>6} {100 * np.mean(m <= SUCCESS_MM):>7.0f}% {np.median(m):>7.2f} "
              f"{np.percentile(m, 90):>7.2f} {m.max():>7.2f} {np.median([r['max_mm'] for r in g]):>8.2f} "
              f"{np.median([r['rot_deg'] for r in g]):>8.2f} {np.median([r['trans_mm'] for r in g]):>9.2f} "
              f"{np.median([r['time_s'] for r in g]):>9.1f} {max(r['time_s'] for r in g):>9.1f} "
              f"{np.median([r['overlap'] for r in g]):>8.3f} {np.median([r['coverage'] for r in g]):>8.3f} "
              f"{np.median(conf) if conf else float('nan'):>8.2f} {np.median([r['sensitivity'] for r in g]):>8.3f}")
    print(f"errors in mm (mean displacement of the CT surface; success: ≤ {SUCCESS_MM:g} mm), rotation in degrees, "
          f"times in seconds; overlap, coverage, confidence, sensitivity: medians of the registrations' own figures")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", default=CASES, help=f"comma-separated (default: {CASES})")
    p.add_argument("--targets", default="raw", help="raw, mesh or raw,mesh (default: raw)")
    p.add_argument("--real", type=Path, default=None, help="folder of the real clouds and their CT")
    p.add_argument("--fibula-cloud", type=Path, default=None, help="the fibula sweep's cloud (mm, CT frame)")
    p.add_argument("--fibula-ct", type=Path, default=None, help="the fibula's CT mesh")
    p.add_argument("--bones", type=Path, default=None, help="folder of the bone models (simulated cases)")
    p.add_argument("--cache", type=Path, default=None, help="folder for simulated sweeps and reconstructions")
    p.add_argument("--starts", type=int, default=50, help="random starts per case and target (default 50)")
    p.add_argument("--max-deg", type=float, default=45.0, help="largest start rotation (default 45°)")
    p.add_argument("--max-mm", type=float, default=50.0, help="largest start translation (default 50 mm)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts (default 0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="registration option")
    p.add_argument("--floor", action="store_true", help="add the refinement from the true pose")
    p.add_argument("--icp-only", action="store_true", help="add the refinement alone from each start")
    p.add_argument("--threads", type=int, default=None, help="NumPy and KD-tree threads (default: all)")
    p.add_argument("--json", type=Path, default=None, help="append each registration as a JSON line")
    p.add_argument("--pictures", type=Path, default=None,
                   help="folder for a picture of each case's first registration (the CT in place)")
    p.add_argument("--verbose", action="store_true", help="one line per registration on stderr")
    args = p.parse_args()
    args.cases = [c for c in args.cases.split(",") if c]
    args.targets = [t for t in args.targets.split(",") if t]
    if set(args.targets) - {"raw", "mesh"}:
        raise SystemExit("--targets: raw, mesh or raw,mesh")
    if "mesh" in args.targets and not args.cache:
        raise SystemExit("--targets mesh needs --cache (the reconstructions are kept there)")
    args.workers = args.threads or -1
    rows = []
    for name in args.cases:
        rows += run_case(name, args)
    if rows:
        print_table(rows)


if __name__ == "__main__":
    _threads = next((sys.argv[i + 1] for i, a in enumerate(sys.argv[:-1]) if a == "--threads"), None)
    if _threads:  # before NumPy loads its BLAS
        for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[_var] = _threads
    main()
