"""Why a preset loses surface on a noisy sweep: the trained field at the truth, in the holes and not.

For each preset, the field is trained on one input of ``bench_robust.py`` (a bone at a level) and
the truth is sampled by area. A truth sample is in a *hole* when the mesh is more than 2 mm from it.
Per preset the table gives, for holes and covered truth: the field ``u`` at the truth (mm; 0 on a
perfect field), the gradient's alignment with the true normal ``|cos(∇u, n)|`` (1 on a distance
field; near 0 the gradient runs along the surface and no crossing is found there), ``|∇u|`` (1 on
a distance field) and the distance to the nearest input point (mm; large: a gap in the data).

    python benchmarks/diagnose_robust.py --bone pelvis --level hard --presets fast,robust \\
        --picture holes_pelvis.png

The picture shows the truth coloured by its distance to each preset's mesh (one column each).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_robust import make_input  # noqa: E402


def field_at_truth(rec, truth, samples: int, points_mm: np.ndarray) -> dict[str, np.ndarray]:
    """Per truth sample: distance to the mesh, u (mm), |cos(∇u, n)|, |∇u| and distance to the input."""
    import torch
    import trimesh
    from scipy.spatial import cKDTree

    x, face = trimesh.sample.sample_surface(truth, samples, seed=0)
    mesh_pts, _ = trimesh.sample.sample_surface(rec.mesh, 4 * samples, seed=1)
    unit = torch.as_tensor(rec.normalizer.forward(x))
    u, g = rec.field.value_and_grad(unit)
    g = g.numpy()
    norm = np.linalg.norm(g, axis=1)
    return {"to_mesh": cKDTree(mesh_pts).query(x)[0],
            "u_mm": u.numpy() * rec.normalizer.scale,
            "cos": np.abs(np.einsum("ij,ij->i", g, truth.face_normals[face])) / np.maximum(norm, 1e-12),
            "grad": norm,
            "to_data": cKDTree(points_mm).query(x)[0]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bone", default="pelvis")
    p.add_argument("--level", default="hard")
    p.add_argument("--presets", default="fast,robust")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=100_000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--cache", type=Path, default=Path("bench_out/robust_inputs"))
    p.add_argument("--picture", type=Path, help="PNG: the truth coloured by its distance to each mesh")
    args = p.parse_args()
    import torch

    import ultraboneudf

    torch.set_num_threads(args.threads)
    points, probe, truth, frames = make_input(args.bone, args.level, args.seed, args.cache)
    print(f"{args.bone} {args.level} (seed {args.seed}): {len(points)} points, truth {truth.area:.0f} mm²")
    print("| preset | truth | share | u mm (median / P90) | abs cos(grad u, n) (median) | abs grad u (median) "
          "| to input mm (median) |")
    print("|---|---|---|---|---|---|---|")
    columns = {}
    for name in args.presets.split(","):
        rec = ultraboneudf.reconstruct(points, preset=name, device="cpu", seed=args.seed, probe_positions=probe,
                                       frame_index=frames)
        stats = field_at_truth(rec, truth, args.samples, points)
        hole = stats["to_mesh"] > 2.0
        for label, sel in (("holes", hole), ("covered", ~hole)):
            if not sel.any():
                continue
            u = stats["u_mm"][sel]
            print(f"| {name} | {label} | {sel.mean():.1%} | {np.median(u):.2f} / {np.percentile(u, 90):.2f} "
                  f"| {np.median(stats['cos'][sel]):.2f} | {np.median(stats['grad'][sel]):.2f} "
                  f"| {np.median(stats['to_data'][sel]):.2f} |")
        columns[name] = rec.mesh
    if args.picture:
        from PIL import Image

        import trimesh

        from ultraboneudf.evaluation.render import render_grid_image

        # one column per preset: the truth coloured by its distance to that preset's mesh
        tiles = [render_grid_image({name: truth}, trimesh.sample.sample_surface(mesh, 400_000, seed=0)[0],
                                   views=("front", "top"))
                 for name, mesh in columns.items()]
        canvas = Image.new("RGB", (sum(t.width for t in tiles), max(t.height for t in tiles)), "white")
        x = 0
        for tile in tiles:
            canvas.paste(tile, (x, 0))
            x += tile.width
        args.picture.parent.mkdir(parents=True, exist_ok=True)
        canvas.save(args.picture)
        print(f"wrote {args.picture}")


if __name__ == "__main__":
    main()
