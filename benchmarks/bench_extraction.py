"""Compare the extraction modes on exact analytic UDFs.

For every field × mode × depth: area / true area, edges with more than two faces, duplicate faces,
boundary loops, the largest vertex distance to the true surface (in leaf cells) and the wall time.

Modes:
    faithful-dmu  DualMesh-UDF with the official DMU driver values (§2.11)
    faithful-ubu  DualMesh-UDF as UltraBoneUDF calls it (§1.8)
    thinned       an earlier option, kept here for comparison only: faithful vertices,
                  only leaves whose vertex lies in their own cell, faithful quads and rules,
                  coincident vertices merged, over-shared edges resolved by face-centre UDF
    clean-mass    ``mode="clean"`` with mass-point vertices (``clean.vertex="mass"``)
    clean         ``mode="clean"`` as shipped (UltraBoneUDF thresholds)

    .venv/bin/python benchmarks/bench_extraction.py                 # depths 7 and 8
    .venv/bin/python benchmarks/bench_extraction.py --depths 7 8 9 --device cuda
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from ultraboneudf.config import DMU_DEFAULTS, CleanConfig, ExtractConfig
from ultraboneudf.extraction import extract_mesh, mesh_quality
from ultraboneudf.extraction.dualmesh import edge_crossing as clean
from ultraboneudf.extraction import dualmesh as dm
from ultraboneudf.fields import DiscUDF, PlaneUDF, SphereUDF, TorusUDF
from ultraboneudf.fields.analytic import sphere_area, torus_area

FIELDS = {
    "sphere r=0.3": (lambda dev: SphereUDF(0.3, device=dev), sphere_area(0.3)),
    "disc r=0.4": (lambda dev: DiscUDF(0.4, device=dev), math.pi * 0.4**2),
    "torus 0.4/0.1": (lambda dev: TorusUDF(0.4, 0.1, device=dev), torus_area(0.4, 0.1)),
    "plane z=0.1": (lambda dev: PlaneUDF(offset=0.1, device=dev), 4.0),
}

MODES = {
    "faithful-dmu": lambda d: ExtractConfig(**{**DMU_DEFAULTS, "max_depth": d}),
    "faithful-ubu": lambda d: ExtractConfig(max_depth=d),
    "thinned": lambda d: ExtractConfig(max_depth=d),
    "clean-mass": lambda d: ExtractConfig(max_depth=d, mode="clean"),
    "clean": lambda d: ExtractConfig(max_depth=d, mode="clean"),
}


def thinned(field, cfg: ExtractConfig):
    """Issue #8's first suggestion, built from the faithful pieces (for comparison only)."""
    lat = dm.Lattice.from_config(cfg)
    h = lat.cell_size()
    ijk = dm.band_leaves(field, cfg)
    if ijk.shape[0] == 0:
        return None
    verts = dm.solve_leaves(dm.sample_leaves(field, cfg, ijk), ijk, cfg)
    lo, hi = lat.leaf_boxes(ijk)
    own = verts.has & ((verts.position > lo - 1e-4 * h) & (verts.position < hi + 1e-4 * h)).all(1)
    pos = verts.position[own]
    faces, _ = dm.triangulate_dmu(pos, verts.kind[own], verts.direction[own], dm.dual_quads(ijk[own], lat.depth))
    rep, faces = dm.merge_vertices(pos, faces, 1e-3 * h)
    pos = pos[rep]
    faces, _ = clean.resolve_nonmanifold(field, cfg, pos, clean._drop_bad_faces(pos, faces, h))
    return dm.build_mesh(pos, faces)


def run(field_name: str, mode: str, depth: int, device: str) -> dict:
    """One extraction and its figures."""
    make, true_area = FIELDS[field_name]
    field = make(device)
    cfg = MODES[mode](depth)
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    options = CleanConfig(vertex="mass") if mode == "clean-mass" else None
    mesh = thinned(field, cfg) if mode == "thinned" else extract_mesh(field, cfg, clean=options)
    if device == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    q = mesh_quality(mesh)
    err = float("nan")
    if mesh is not None:
        x = torch.as_tensor(mesh.vertices, dtype=torch.float64, device=device)
        err = field.value(x).abs().max().item() / (2.0 / 2**depth)
    return {"field": field_name, "mode": mode, "depth": depth, "area_ratio": q["area"] / true_area,
            "nonmanifold": q["nonmanifold_edges"], "duplicates": q["duplicate_faces"],
            "loops": q["boundary_loops"], "err_cells": err, "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--depths", type=int, nargs="+", default=[7, 8])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--fields", nargs="+", default=list(FIELDS), choices=list(FIELDS))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    header = ("| field | mode | depth | area ratio | non-manifold edges | duplicate faces | boundary loops "
              "| max vertex error (cells) | seconds |")
    print(header)
    print("|" + "|".join(["---"] * 9) + "|")
    for name in args.fields:
        for mode in args.modes:
            for depth in args.depths:
                r = run(name, mode, depth, args.device)
                print(f"| {r['field']} | {r['mode']} | {r['depth']} | {r['area_ratio']:.4f} | {r['nonmanifold']} "
                      f"| {r['duplicates']} | {r['loops']} | {r['err_cells']:.4f} | {r['seconds']:.2f} |",
                      flush=True)


if __name__ == "__main__":
    main()
