"""The per-leaf vertex of DualMesh-UDF (docs/ALGORITHMS.md §2.6): a batched QEF in float64 over the
leaves' projections, typed corner, edge or plane by its singular values."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...config import ExtractConfig
from .octree import Lattice, LeafSamples


# Vertex types of the QEF solve (§2.6); NO_VERTEX marks a leaf without a vertex.
CORNER, EDGE, PLANE, NO_VERTEX = 0, 1, 2, -1
TYPE_NAMES = {CORNER: "corner", EDGE: "edge", PLANE: "plane"}


_PARALLEL_TOL = 1e-4  # |d_k| below this: line/plane parallel to an axis (unit vectors, §2.6)
_ON_CELL = 1e-5       # "inside" window that means "on the cell's own faces/edges"
_FLAG_WINDOW = 1e-4   # inside-flag window of EDGE and PLANE vertices
_MASS_WINDOW = 0.01   # window of the projections averaged into the mass point
_LEAF_CHUNK = 1 << 15  # leaves per QEF batch: bounds the (chunk, K, 3) float64 temporaries


def _fallback_windows() -> tuple[float, ...]:
    """Windows of the fallback solve: 1e-4, then 0.02 + 0.05·k while < 0.3 (accumulated in float
    exactly as the reference loop does, so the strict box tests see the same numbers)."""
    out, w = [1e-4], 0.02
    while w < 0.3:
        out.append(w)
        w += 0.05
    return tuple(out)


FALLBACK_WINDOWS = _fallback_windows()




# --------------------------------------------------------------------------------------------
# §2.6 per-leaf QEF
# --------------------------------------------------------------------------------------------

@dataclass
class LeafVertices:
    """Per-leaf result of the QEF solve: position (L, 3) float64 (NaN without a vertex), type
    (L,) int8 in {CORNER, EDGE, PLANE, NO_VERTEX}, direction (L, 3) float64 (line direction for
    EDGE, plane normal for PLANE, zero otherwise; unit length, sign arbitrary)."""

    position: torch.Tensor
    kind: torch.Tensor
    direction: torch.Tensor

    @property
    def has(self) -> torch.Tensor:
        """(L,) bool: the leaf owns a vertex."""
        return self.kind >= 0


def _inside(x: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, f: float) -> torch.Tensor:
    """Strict box test ``lo − f·e < x < hi + f·e`` on all three axes; ``lo``, ``hi`` broadcast
    against ``x`` (..., 3). NaN is outside."""
    e = hi - lo
    return ((x > lo - f * e) & (x < hi + f * e)).all(-1)


def _pick(points: torch.Tensor, usable: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
          factor: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean of the candidate points (B, C, 3) on the cell (window 1e-5) or, if there are none,
    within the window ``factor``; returns the mean (B, 3) and whether any candidate was taken.
    Candidates must be finite (they are: parallel cases use a unit denominator and are masked)."""
    lo, hi = lo[:, None], hi[:, None]
    on = usable & _inside(points, lo, hi, _ON_CELL)
    near = usable & _inside(points, lo, hi, factor)
    take = torch.where(on.any(1, keepdim=True), on, near)
    count = take.sum(1, keepdim=True)
    return (points * take[..., None]).sum(1) / count.clamp_min(1), count.squeeze(1) > 0


def _line_hits(v: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Intersections (B, 6, 3) of the lines ``v + t·d`` with the six face planes of the boxes,
    and (B, 6) whether each exists (face not parallel to the line)."""
    planes = torch.stack([lo, hi], 1)                                    # (B, 2, 3): side, axis
    parallel = d.abs() < _PARALLEL_TOL                                   # (B, 3)
    t = (planes - v[:, None]) / torch.where(parallel, torch.ones_like(d), d)[:, None]
    pts = v[:, None, None, :] + t[..., None] * d[:, None, None, :]       # (B, side, axis, 3)
    ok = ~parallel[:, None, :].expand(-1, 2, -1)
    return pts.reshape(-1, 6, 3), ok.reshape(-1, 6)


def _edge_table() -> tuple[torch.Tensor, torch.Tensor]:
    """The twelve cell-edge lines: (12, 3) one-hot of the free axis and (12, 3) 0/1 choice of lo/hi
    for the two fixed coordinates (0 on the free axis)."""
    free, side = [], []
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        for sa in (0, 1):
            for sb in (0, 1):
                f, s = [0, 0, 0], [0, 0, 0]
                f[k], s[a], s[b] = 1, sa, sb
                free.append(f)
                side.append(s)
    return torch.tensor(free, dtype=torch.float64), torch.tensor(side, dtype=torch.float64)


_EDGE_FREE, _EDGE_SIDE = _edge_table()


def _plane_hits(v: torch.Tensor, n: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
    """Intersections (B, 12, 3) of the planes through ``v`` with normal ``n`` and the twelve
    edge lines of the boxes, and (B, 12) whether each exists (edge not parallel to the plane)."""
    free, side = _EDGE_FREE.to(v.device), _EDGE_SIDE.to(v.device)
    base = lo[:, None] + side * (hi - lo)[:, None]                       # fixed coordinates
    n_free = (n[:, None, :] * free).sum(-1)                              # (B, 12)
    parallel = n_free.abs() < _PARALLEL_TOL
    rest = ((base - v[:, None]) * n[:, None, :] * (1.0 - free)).sum(-1)  # n·(p − v) over fixed axes
    t = -rest / torch.where(parallel, torch.ones_like(n_free), n_free)
    pts = base * (1.0 - free) + (v[:, None, :] + t[..., None]) * free
    return pts, ~parallel


@dataclass
class _Solve:
    position: torch.Tensor  # (B, 3)
    ok: torch.Tensor        # (B,) a vertex was produced (acceptance window passed, finite)
    kind: torch.Tensor      # (B,) int64 CORNER/EDGE/PLANE (meaningless where not ok)
    direction: torch.Tensor  # (B, 3)
    flag: torch.Tensor      # (B,) inside-flag


def qef_solve(M: torch.Tensor, r: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
              cfg: ExtractConfig) -> _Solve:
    """SOLVE of §2.6 for a batch of B cells, in coordinates relative to the mass point.

    ``M = AᵀA`` (B, 3, 3) and ``r = Aᵀb`` (B, 3) are the normal equations of the tangent planes
    taking part (rows outside the solve contribute nothing, like zero rows of A), ``lo``/``hi``
    (B, 3) the shifted cell corners.

    A batched symmetric eigen-solve in float64 replaces the thin SVD of A: σ_i = √λ_i, the
    relative cut ``σ_i > τ_sv·σ_1`` becomes ``λ_i > τ_sv²·λ_1`` and the truncated pseudo-inverse
    solution is ``Σ_kept (v_iᵀAᵀb / λ_i)·v_i`` — the same vertex (§2.12). σ_1 = 0 or any
    non-finite entry gives no vertex."""
    finite = torch.isfinite(M).all(2).all(1) & torch.isfinite(r).all(1)
    M = torch.where(finite[:, None, None], M, torch.zeros_like(M))  # keep eigh away from NaN
    r = torch.where(finite[:, None], r, torch.zeros_like(r))
    lam, vec = torch.linalg.eigh(M)                     # ascending; columns are eigenvectors
    lam = lam.clamp_min(0.0)
    lmax = lam[:, 2]
    keep = lam > (cfg.sv_threshold ** 2) * lmax[:, None]
    nkeep = keep.sum(1)
    coef = (vec.transpose(1, 2) @ r[..., None]).squeeze(-1)
    coef = torch.where(keep, coef / torch.where(keep, lam, torch.ones_like(lam)), torch.zeros_like(lam))
    v = (vec * coef[:, None, :]).sum(2)
    kind = torch.where(nkeep == 3, CORNER, torch.where(nkeep == 2, EDGE, PLANE))
    normal, line = vec[:, :, 2], vec[:, :, 0]
    direction = torch.where((kind == PLANE)[:, None], normal,
                            torch.where((kind == EDGE)[:, None], line, torch.zeros_like(line)))
    # Placement (§2.6 step 5), each rule on the rows of its type.
    position = v.clone()
    accepted = _inside(v, lo, hi, cfg.corner_factor)                    # CORNER rule
    for k, hits, factor in ((EDGE, _line_hits, cfg.edge_factor), (PLANE, _plane_hits, cfg.plane_factor)):
        rows = (kind == k).nonzero().squeeze(1)
        if rows.numel():
            position[rows], accepted[rows] = _pick(*hits(v[rows], direction[rows], lo[rows], hi[rows]),
                                                   lo[rows], hi[rows], factor)
    flag = torch.where(kind == CORNER, _inside(v, lo, hi, _ON_CELL), _inside(position, lo, hi, _FLAG_WINDOW))
    ok = finite & (lmax > 0) & (nkeep > 0) & accepted & torch.isfinite(position).all(1)
    return _Solve(position, ok, kind, direction, flag)


def _solve_cells(g: torch.Tensor, plane: torch.Tensor, pi: torch.Tensor, V: torch.Tensor,
                 lo: torch.Tensor, hi: torch.Tensor, h: float, cfg: ExtractConfig):
    """§2.6 for a batch of B cells of edge ``h``.

    ``g`` (B, K, 3) unit gradients (zero rows allowed), ``plane`` (B, K) tangent-plane offsets
    ``ĝ·x − u``, ``pi`` (B, K, 3) projections, ``V`` (B, K) the valid-sample filter of step 1,
    ``lo``/``hi`` (B, 3) cell corners. Returns position (B, 3) (NaN where none), kind (B,) int64
    (NO_VERTEX where none) and direction (B, 3).

    The QEF only needs the normal equations: with rows masked by ``w``, ``M = Σ w ĝĝᵀ`` and, for
    planes shifted by the mass point ``c``, ``Aᵀb = Σ w ĝ (ĝ·x − u) − M c``."""
    # How far (in cells) each projection lies outside its cell: inside(π, f) ⇔ out < f.
    out = torch.maximum(lo[:, None] - pi, pi - hi[:, None]).amax(-1) / h
    # Step 2: mass point = mean of the valid projections inside the cell (window 0.01), else centre.
    in_mass = V & (out < _MASS_WINDOW)
    n_mass = in_mass.sum(1, keepdim=True)
    mass = (pi * in_mass[..., None]).sum(1) / n_mass.clamp_min(1)
    c = torch.where(n_mass > 0, mass, 0.5 * (lo + hi))
    # Step 3: shift the cell so that the minimum-norm solution is taken relative to c.
    los, his = lo - c, hi - c

    def normal_equations(rows, mask, c):
        gw = g[rows] * mask[..., None].to(g.dtype)
        M = gw.transpose(1, 2) @ g[rows]
        r = (gw * plane[rows][..., None]).sum(1) - (M @ c[..., None]).squeeze(-1)
        return M, r

    # Step 4: primary solve over all valid samples, for cells with more than two of them.
    every = slice(None)
    prim = qef_solve(*normal_equations(every, V, c), los, his, cfg)
    ok = (V.sum(1) > 2) & prim.ok
    position = torch.where(ok[:, None], prim.position + c, torch.full_like(c, float("nan")))
    kind = torch.where(ok, prim.kind, NO_VERTEX)
    direction = torch.where(ok[:, None], prim.direction, torch.zeros_like(c))
    # Step 5: fallback on projections (nearly) inside the cell; the first window holding > 2 wins.
    sub = (~ok).nonzero().squeeze(1)
    if sub.numel() == 0:
        return position, kind, direction
    Vs, outs = V[sub], out[sub]
    Vp = Vs & (outs < FALLBACK_WINDOWS[0])
    for w in FALLBACK_WINDOWS[1:]:
        few = Vp.sum(1) <= 2
        if not bool(few.any()):
            break
        Vp = torch.where(few[:, None], Vs & (outs < w), Vp)
    enough = Vp.sum(1) > 2
    sub, Vp = sub[enough], Vp[enough]
    if sub.numel() == 0:
        return position, kind, direction
    fb = qef_solve(*normal_equations(sub, Vp, c[sub]), los[sub], his[sub], cfg)
    acc = fb.ok & fb.flag
    take = sub[acc]
    position[take] = fb.position[acc] + c[take]
    kind[take] = fb.kind[acc]
    direction[take] = fb.direction[acc]
    return position, kind, direction


def solve_leaves(samples: LeafSamples, ijk: torch.Tensor, cfg: ExtractConfig) -> LeafVertices:
    """Per-leaf vertex, type and direction (§2.6) for all leaves ``ijk`` (L, 3), in float64.

    Leaves are processed in chunks of ``2^15`` to bound the (chunk, K, 3) temporaries; everything
    inside a chunk is batched."""
    lat = Lattice.from_config(cfg)
    L = ijk.shape[0]
    device = ijk.device
    position = torch.full((L, 3), float("nan"), dtype=torch.float64, device=device)
    kind = torch.full((L,), NO_VERTEX, dtype=torch.int8, device=device)
    direction = torch.zeros((L, 3), dtype=torch.float64, device=device)
    for start in range(0, L, _LEAF_CHUNK):
        sl = slice(start, min(L, start + _LEAF_CHUNK))
        ids = samples.ids[sl]
        lo, hi = lat.leaf_boxes(ijk[sl])
        p, k, d = _solve_cells(samples.grad[ids], samples.plane[ids], samples.proj[ids],
                               samples.usable[ids], lo, hi, lat.cell_size(), cfg)
        position[sl], kind[sl], direction[sl] = p, k.to(torch.int8), d
    return LeafVertices(position, kind, direction)
