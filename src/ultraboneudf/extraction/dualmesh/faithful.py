"""DualMesh-UDF as the reference extracts (docs/ALGORITHMS.md §2): the band's leaves, their QEF
vertices, the dual quads and the triangulation rules of §2.9."""

from __future__ import annotations

import torch
import trimesh

from ...config import ExtractConfig
from ...fields.base import Field
from ...progress import QUIET, Progress
from .mesh import build_mesh, dual_quads, merge_vertices
from .octree import Lattice, band_samples
from .qef import EDGE, PLANE, solve_leaves


# --------------------------------------------------------------------------------------------
# §2.9 triangulation
# --------------------------------------------------------------------------------------------

def _unit(v: torch.Tensor) -> torch.Tensor:
    """Unit vectors along the last axis; a zero vector stays zero (Eigen's normalized())."""
    n = v.norm(dim=-1, keepdim=True)
    return torch.where(n > 0, v / torch.where(n > 0, n, torch.ones_like(n)), torch.zeros_like(v))


def _axis_normal(points: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """The normal the reference's SVD returns where the points do not fix one.

    ``points`` (..., n, 3), ``normal`` (..., 3) the normal found otherwise. The reference takes the
    last right singular vector of Eigen's ``JacobiSVD`` of the centred points; when they coincide or
    lie on a line along a coordinate axis (a flat surface on a lattice plane, whose two stacked band
    layers give quads of coincident vertex pairs) that vector is not determined by the geometry but
    by Eigen's column order: no rotation happens, so it is the z axis, or the x axis for a line
    along z. Other collinear points (a line off the axes) are left to ``normal``: there Eigen's
    choice depends on rounding noise in its pivoting."""
    centred = points - points.mean(-2, keepdim=True)
    moves = (centred != 0).any(-2)                              # (..., 3) which coordinates vary
    on_axis = moves.sum(-1) <= 1
    axis = torch.zeros_like(normal)
    axis[..., 2] = 1.0
    along_z = moves[..., 2]
    axis[along_z] = torch.tensor([1.0, 0.0, 0.0], dtype=normal.dtype, device=normal.device)
    return torch.where(on_axis[..., None], axis, normal)


def triangulate_dmu(position: torch.Tensor, kind: torch.Tensor, direction: torch.Tensor,
                    quads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The quad → triangle rules of §2.9 as boolean algebra.

    ``position`` (N, 3), ``kind`` (N,), ``direction`` (N, 3) per vertex; ``quads`` (Q, 4).
    Returns faces (F, 3) int64 (vertex indices) and (Q,) bool whether each quad was kept."""
    P, T, Dd = position[quads], kind[quads].to(torch.int64), direction[quads]
    is_p, is_e = T == PLANE, T == EDGE
    # 1. coplanarity from the singular values of the centred 4×3 matrix. An SVD of the matrix
    #    itself, not an eigen-solve of its Gram matrix: nearly collinear quads (two stacked band
    #    layers) have s2 ≈ 1e-9·s1, which squaring would drown in rounding.
    _, sv, vt = torch.linalg.svd(P - P.mean(1, keepdim=True), full_matrices=False)
    coplanar = sv[:, 2] < 0.25 * sv[:, 0]
    # 2. coplanar quad: every PLANE normal near the quad normal, every EDGE line near the plane.
    quad_n = _axis_normal(P, vt[:, 2])
    dots = (Dd * quad_n[:, None, :]).sum(-1).abs()
    cop_ok = ~((is_p & (dots < 0.85)) | (is_e & (dots > 0.5))).any(1)
    # 3. non-coplanar quad: PLANE vertex i checked against triangle (v_i, v_i+1, v_i+3).
    nxt, prv = P.roll(-1, 1), P.roll(1, 1)
    tri_n = _axis_normal(torch.stack([P, nxt, prv], -2), _unit(torch.linalg.cross(nxt - P, prv - P)))
    plane_fail = (is_p & ((Dd * tri_n).sum(-1).abs() < 0.85)).any(1)
    n_plane = is_p.sum(1)
    opposite = (is_p[:, 0] & is_p[:, 2]) | (is_p[:, 1] & is_p[:, 3])
    pattern_ok = (n_plane <= 1) | ((n_plane == 2) & opposite)
    nc_ok = ~plane_fail & pattern_ok
    # t = the last PLANE vertex of the scan (single one, or the later of two opposite ones).
    t = torch.where(n_plane == 2, torch.where(is_p[:, 3], 3, 2), is_p.to(torch.int64).argmax(1))
    # Candidate triangle pairs, selected per quad.
    q = quads
    rolled = torch.gather(q, 1, (t[:, None] + torch.arange(4, device=q.device)) % 4)  # q[t], q[t+1], …
    plane_pair = (rolled[:, [0, 1, 3]], rolled[:, [1, 2, 3]])
    diag02 = (q[:, [0, 1, 2]], q[:, [2, 3, 0]])
    diag13 = (q[:, [0, 1, 3]], q[:, [1, 2, 3]])
    edge_diag = is_e[:, 0] & is_e[:, 2]
    use_plane = (~coplanar) & (n_plane > 0)
    use_02 = coplanar | (~coplanar & (n_plane == 0) & edge_diag)
    first = torch.where(use_plane[:, None], plane_pair[0], torch.where(use_02[:, None], diag02[0], diag13[0]))
    second = torch.where(use_plane[:, None], plane_pair[1], torch.where(use_02[:, None], diag02[1], diag13[1]))
    keep = torch.where(coplanar, cop_ok, nc_ok)
    faces = torch.stack([first[keep], second[keep]], 1).reshape(-1, 3)
    return faces, keep


# --------------------------------------------------------------------------------------------
# The extractor
# --------------------------------------------------------------------------------------------

def dualmesh_udf(field: Field, cfg: ExtractConfig, progress: Progress = QUIET) -> trimesh.Trimesh | None:
    """DualMesh-UDF (§2) on ``field``, faithful to the reference.

    Args:
        field: the UDF; evaluated on ``field.device`` in batches of ``cfg.batch`` points.
        cfg: octree depth, thresholds and factors (all in field units).
        progress: one stage, advancing per octree level and per later step.

    Returns:
        The mesh in the field's coordinates (``process=False``: vertices unmerged beyond
        ``ε_dup``, not oriented, possibly non-manifold), or ``None`` when no cell survives, no
        leaf owns a vertex or no face is emitted. ``mesh.metadata`` holds ``vertex_type``
        (V,) int8 (CORNER=0, EDGE=1, PLANE=2), ``vertex_direction`` (V, 3) and counters
        (``leaves``, ``vertex_cells``, ``quads``, ``quads_kept``).
    """
    lat = Lattice.from_config(cfg)
    with progress.stage("DualMesh-UDF", total=lat.depth + 1 + 5) as advance:
        band = band_samples(field, cfg, advance)
        if band is None:
            return None
        ijk, samples = band
        verts = solve_leaves(samples, ijk, cfg)
        advance(1)
        has = verts.has
        if not bool(has.any()):
            return None
        cells = ijk[has]
        position, kind, direction = verts.position[has], verts.kind[has], verts.direction[has]
        quads = dual_quads(cells, lat.depth)
        advance(1)
        faces, kept = triangulate_dmu(position, kind, direction, quads)
        advance(1)
        rep, faces = merge_vertices(position, faces, cfg.dedup_eps)
        meta = {"extractor": "dualmesh-udf", "mode": "faithful", "leaves": int(ijk.shape[0]),
                "vertex_cells": int(cells.shape[0]), "quads": int(quads.shape[0]),
                "quads_kept": int(kept.sum())}
        mesh = build_mesh(position[rep], faces, meta, vertex_type=kind[rep],
                          vertex_direction=direction[rep])
        advance(1)
    return mesh
