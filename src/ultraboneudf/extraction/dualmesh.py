"""DualMesh-UDF mesh extraction (docs/ALGORITHMS.md §2), vectorised in torch over a sparse octree band.

The reference (DMU, C++) walks an octree; here every stage is a batched tensor operation on the
cells that survive subdivision (§2.12): int64 cell keys, one batched field query per level, the
``L × K`` leaf samples (``K = (2^s + 1)³ = 27``) uniqued and evaluated once, a batched per-leaf
QEF in float64, dual quads by ``searchsorted`` on sorted keys and the triangulation rules of §2.9
as boolean algebra. Nothing is indexed by the full lattice, so memory follows the band size.

Units: all coordinates, sizes and thresholds are in the field's own units (unit space in the
pipeline, §0.1). Integer cell coordinates ``ijk`` at depth ``d`` index cells of edge
``h_d = (hi − lo) / 2^d`` with minimum corner ``lo + h_d·ijk``.

The building blocks (:func:`band_leaves`, :func:`sample_leaves`, :func:`solve_leaves`,
:func:`cell_ring`, :func:`triangulate_dmu`, :func:`merge_vertices`) are shared with the clean
extractor (:mod:`.clean`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
import trimesh

from ..config import ExtractConfig
from ..fields.base import Field
from ..progress import QUIET, Progress

# Vertex types of the QEF solve (§2.6); NO_VERTEX marks a leaf without a vertex.
CORNER, EDGE, PLANE, NO_VERTEX = 0, 1, 2, -1
TYPE_NAMES = {CORNER: "corner", EDGE: "edge", PLANE: "plane"}

_PARALLEL_TOL = 1e-4  # |d_k| below this: line/plane parallel to an axis (unit vectors, §2.6)
_ON_CELL = 1e-5       # "inside" window that means "on the cell's own faces/edges"
_FLAG_WINDOW = 1e-4   # inside-flag window of EDGE and PLANE vertices
_MASS_WINDOW = 0.01   # window of the projections averaged into the mass point
_LEAF_CHUNK = 1 << 15  # leaves per QEF batch: bounds the (chunk, K, 3) float64 temporaries
_MAX_BITS = 21        # 3 coordinates × 21 bits fit in a non-negative int64


def _fallback_windows() -> tuple[float, ...]:
    """Windows of the fallback solve: 1e-4, then 0.02 + 0.05·k while < 0.3 (accumulated in float
    exactly as the reference loop does, so the strict box tests see the same numbers)."""
    out, w = [1e-4], 0.02
    while w < 0.3:
        out.append(w)
        w += 0.05
    return tuple(out)


FALLBACK_WINDOWS = _fallback_windows()


def _noop(n: float = 1) -> None:
    return None


# --------------------------------------------------------------------------------------------
# Lattice geometry and integer keys
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Lattice:
    """The octree's geometry: domain ``[lo, hi]³``, maximum depth ``D``, sampling depth ``s``."""

    depth: int
    sub: int
    lo: float
    hi: float

    @classmethod
    def from_config(cls, cfg: ExtractConfig) -> "Lattice":
        lo, hi = (float(v) for v in cfg.domain)
        depth, sub = int(cfg.max_depth), int(cfg.sampling_depth)
        if not hi > lo:
            raise ValueError(f"extraction domain must have hi > lo, got {cfg.domain}")
        if depth < 0 or sub < 0 or depth + sub + 1 > _MAX_BITS:
            raise ValueError(f"need 0 ≤ max_depth, 0 ≤ sampling_depth and max_depth + sampling_depth"
                             f" ≤ {_MAX_BITS - 1}; got {depth}, {sub}")
        return cls(depth, sub, lo, hi)

    def cell_size(self, d: int | None = None) -> float:
        """Edge length of a depth-``d`` cell (default: a leaf, ``d = D``)."""
        return (self.hi - self.lo) / 2 ** (self.depth if d is None else d)

    @property
    def step(self) -> float:
        """Spacing of the leaf sample sub-lattice, ``h_D / 2^s``."""
        return self.cell_size() / 2 ** self.sub

    @property
    def bits(self) -> int:
        """Bits per coordinate of sample-lattice keys (indices 0 … 2^(D+s) inclusive)."""
        return self.depth + self.sub + 1

    @property
    def cell_bits(self) -> int:
        """Bits per coordinate of leaf-cell keys."""
        return self.depth + 1

    def sample_points(self, idx: torch.Tensor) -> torch.Tensor:
        """Coordinates (..., 3) float64 of sample-lattice indices ``idx`` (..., 3)."""
        return self.lo + self.step * idx.to(torch.float64)

    def leaf_boxes(self, ijk: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Minimum and maximum corners (L, 3) of the leaves ``ijk`` (L, 3), computed exactly like
        the sample coordinates so that corner samples and box faces coincide bit for bit."""
        m = 1 << self.sub
        return self.sample_points(ijk * m), self.sample_points((ijk + 1) * m)


def pack(ijk: torch.Tensor, bits: int) -> torch.Tensor:
    """Pack non-negative integer coordinates (..., 3) into int64 keys (...,); ``bits`` per axis.

    Packing is linear as long as no coordinate overflows its field, which lets callers add packed
    offsets to packed bases."""
    return (ijk[..., 0] << (2 * bits)) | (ijk[..., 1] << bits) | ijk[..., 2]


def unpack(keys: torch.Tensor, bits: int) -> torch.Tensor:
    """Inverse of :func:`pack`: keys (...,) → coordinates (..., 3) int64."""
    mask = (1 << bits) - 1
    return torch.stack([(keys >> (2 * bits)) & mask, (keys >> bits) & mask, keys & mask], dim=-1)


def band_threshold(depth: int, cfg: ExtractConfig) -> float:
    """Subdivision threshold of §2.3 at ``depth``: half the cell diagonal plus the margin μ
    (field units). A cell survives iff ``u(centre) <`` this value (strict)."""
    lo, hi = cfg.domain
    return math.sqrt(3.0) / 2.0 * (hi - lo) / 2 ** depth + cfg.margin


# --------------------------------------------------------------------------------------------
# §2.3 adaptive subdivision
# --------------------------------------------------------------------------------------------

_CHILDREN = torch.tensor([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)],
                         dtype=torch.int64)  # child k = 4·x + 2·y + z


def band_leaves(field: Field, cfg: ExtractConfig,
                advance: Callable[[float], None] = _noop) -> torch.Tensor:
    """Integer coordinates (L, 3) int64 of the depth-``D`` leaves of §2.3, sorted by key.

    Level by level, every active cell's centre is evaluated (one batched query) and the cell kept
    iff ``u(centre) < (√3/2)·h_d + μ``; kept cells below depth ``D`` are replaced by their 8
    children. A failed cell drops its whole subtree, so the result is exactly the reference
    octree's leaves. Levels shallower than ``cfg.band_start_depth`` keep every cell untested (0, the
    reference, tests from the root). Empty (0, 3) when no cell survives some level. Calls
    ``advance(1)`` per level.
    """
    lat = Lattice.from_config(cfg)
    device = torch.device(field.device)
    ijk = torch.zeros((1, 3), dtype=torch.int64, device=device)
    children = _CHILDREN.to(device)
    for d in range(lat.depth + 1):
        if d >= min(cfg.band_start_depth, lat.depth):
            centres = lat.lo + lat.cell_size(d) * (ijk.to(torch.float64) + 0.5)
            u = field.value(centres, chunk=cfg.batch)
            ijk = ijk[u < band_threshold(d, cfg)]  # NaN compares False: such cells are dropped
        advance(1)
        if ijk.shape[0] == 0:
            return ijk
        if d < lat.depth:
            ijk = (2 * ijk[:, None, :] + children[None]).reshape(-1, 3)
    return ijk[torch.argsort(pack(ijk, lat.cell_bits))]


# --------------------------------------------------------------------------------------------
# §2.4–2.5 leaf samples, projections, validity
# --------------------------------------------------------------------------------------------

@dataclass
class LeafSamples:
    """The distinct sample points of all leaves and what the field says there.

    ``ids`` (L, K) int64 maps each leaf's K = (2^s+1)³ samples (offsets {0…2^s}³, x slowest) to
    rows of the other arrays, which hold one entry per distinct sample-lattice point (S of them).
    """

    ids: torch.Tensor      # (L, K) int64
    index: torch.Tensor    # (S, 3) int64 sample-lattice indices
    points: torch.Tensor   # (S, 3) float64 coordinates
    u: torch.Tensor        # (S,) float64 field values
    grad: torch.Tensor     # (S, 3) float64 unit gradients; zero where unusable
    grad_ok: torch.Tensor  # (S,) bool: finite value and finite, non-zero gradient
    proj: torch.Tensor     # (S, 3) float64 projections x − u·ĝ
    plane: torch.Tensor    # (S,) float64 tangent-plane offsets ĝ·x − u (0 where unusable)
    usable: torch.Tensor   # (S,) bool: grad_ok, u > τ_min and u(π) < τ_val (membership of V)


def sample_offsets(sub: int, device: torch.device) -> torch.Tensor:
    """Offsets (K, 3) int64 of a leaf's samples in sample-lattice steps, x slowest."""
    r = torch.arange((1 << sub) + 1, device=device)
    return torch.cartesian_prod(r, r, r).reshape(-1, 3)


def sample_leaves(field: Field, cfg: ExtractConfig, ijk: torch.Tensor) -> LeafSamples:
    """Evaluate the leaf samples of §2.4 once per distinct lattice point, with projections and
    the validity test of §2.5.

    Rows whose value or gradient is not finite, or whose gradient is exactly zero, are unusable:
    they would give NaN or meaningless tangent planes (§2.13). The validity query ``u(π)`` is only
    made for samples that can enter a solve (usable so far and ``u > τ_min``)."""
    lat = Lattice.from_config(cfg)
    m = 1 << lat.sub
    offsets = sample_offsets(lat.sub, ijk.device)
    # pack() is linear without overflow, so base key + offset key = key of the sample.
    keys = pack(ijk * m, lat.bits)[:, None] + pack(offsets, lat.bits)[None, :]
    ukeys, ids = torch.unique(keys, return_inverse=True)
    index = unpack(ukeys, lat.bits)
    points = lat.sample_points(index)
    u, g_raw = field.value_and_grad(points, chunk=cfg.batch)
    u, g_raw = u.to(torch.float64), g_raw.to(torch.float64)
    norm = g_raw.norm(dim=1)
    grad_ok = torch.isfinite(u) & torch.isfinite(g_raw).all(1) & (norm > 0)
    # Exact unit vectors for any non-zero gradient (the reference divides by the norm, by 1 if 0).
    grad = torch.where(grad_ok[:, None], g_raw / torch.where(grad_ok, norm, 1.0)[:, None],
                       torch.zeros_like(g_raw))
    u_ok = torch.where(grad_ok, u, torch.zeros_like(u))
    proj = points - u_ok[:, None] * grad
    plane = (grad * points).sum(1) - u_ok
    usable = grad_ok & (u > cfg.min_udf)
    rows = usable.nonzero().squeeze(1)
    if rows.numel():
        usable[rows] = field.value(proj[rows], chunk=cfg.batch) < cfg.valid_threshold
    return LeafSamples(ids, index, points, u, grad, grad_ok, proj, plane, usable)


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


# --------------------------------------------------------------------------------------------
# §2.8 dual quads
# --------------------------------------------------------------------------------------------

def lookup_cells(keys: torch.Tensor, ijk: torch.Tensor, depth: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (...,) of cells ``ijk`` (..., 3) in the sorted leaf-key array ``keys`` (N,) and
    (...,) whether they exist; cells outside [0, 2^depth)³ never exist."""
    n = 1 << depth
    in_range = ((ijk >= 0) & (ijk < n)).all(-1)
    k = pack(ijk.clamp(0, n - 1), depth + 1)
    if keys.numel() == 0:
        return torch.zeros_like(k), torch.zeros_like(in_range)
    pos = torch.searchsorted(keys, k).clamp_max(keys.numel() - 1)
    return pos, in_range & (keys[pos] == k)


RING_OFFSETS = ((0, 0), (0, 1), (1, 1), (1, 0))  # (Δβ, Δγ) of the four cells around an edge, §2.8 order


def cell_ring(keys: torch.Tensor, base: torch.Tensor, axis: int, depth: int):
    """The four cells around the lattice edges parallel to ``axis`` whose lowest cell is ``base``
    (Q, 3): cells with ``(b, c)`` indices (β, γ), (β, γ+1), (β+1, γ+1), (β+1, γ), where
    ``(b, c)`` follow ``axis`` cyclically (§2.8). Returns indices (Q, 4) into the sorted ``keys``
    and (Q,) whether all four exist."""
    b, c = (axis + 1) % 3, (axis + 2) % 3
    cells = base[:, None, :].repeat(1, 4, 1)
    for j, (db, dc) in enumerate(RING_OFFSETS):
        cells[:, j, b] += db
        cells[:, j, c] += dc
    idx, found = lookup_cells(keys, cells, depth)
    return idx, found.all(1)


def dual_quads(cells: torch.Tensor, depth: int) -> torch.Tensor:
    """Quads (Q, 4) int64 of §2.8 over the vertex-owning leaves ``cells`` (N, 3), sorted by key.

    For every axis and every cell taken as the lowest of a ring of four, one quad when all four
    cells own a vertex, in the exact cyclic order of §2.8. Indices refer to rows of ``cells``."""
    keys = pack(cells, depth + 1)
    quads = []
    for axis in range(3):
        idx, ok = cell_ring(keys, cells, axis, depth)
        quads.append(idx[ok])
    return torch.cat(quads) if quads else torch.zeros((0, 4), dtype=torch.int64, device=cells.device)


# --------------------------------------------------------------------------------------------
# §2.9 triangulation
# --------------------------------------------------------------------------------------------

def _unit(v: torch.Tensor) -> torch.Tensor:
    """Unit vectors along the last axis; a zero vector stays zero (Eigen's normalized())."""
    n = v.norm(dim=-1, keepdim=True)
    return torch.where(n > 0, v / torch.where(n > 0, n, torch.ones_like(n)), torch.zeros_like(v))


def triangulate_dmu(position: torch.Tensor, kind: torch.Tensor, direction: torch.Tensor,
                    quads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The quad → triangle rules of §2.9 as boolean algebra.

    ``position`` (N, 3), ``kind`` (N,), ``direction`` (N, 3) per vertex; ``quads`` (Q, 4).
    Returns faces (F, 3) int64 (vertex indices) and (Q,) bool whether each quad was kept."""
    P, T, Dd = position[quads], kind[quads].to(torch.int64), direction[quads]
    is_p, is_e = T == PLANE, T == EDGE
    # 1. coplanarity from the singular values of the centred 4×3 matrix (eigen route, float64).
    cen = P - P.mean(1, keepdim=True)
    lam, vec = torch.linalg.eigh(cen.transpose(1, 2) @ cen)
    lam = lam.clamp_min(0.0)
    coplanar = lam[:, 0] < 0.0625 * lam[:, 2]       # s3 < 0.25·s1
    # 2. coplanar quad: every PLANE normal near the quad normal, every EDGE line near the plane.
    dots = (Dd * vec[:, None, :, 0]).sum(-1).abs()
    cop_ok = ~((is_p & (dots < 0.85)) | (is_e & (dots > 0.5))).any(1)
    # 3. non-coplanar quad: PLANE vertex i checked against triangle (v_i, v_i+1, v_i+3).
    nxt, prv = P.roll(-1, 1), P.roll(1, 1)
    tri_n = _unit(torch.linalg.cross(nxt - P, prv - P))
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
# §2.10 post-processing
# --------------------------------------------------------------------------------------------

def unique_rows(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Group equal rows of an integer array (N, k).

    Returns ``inverse`` (N,) group ids (groups in lexicographic row order) and ``first`` (G,) the
    lowest row index of each group. Successive stable 1-D sorts replace ``torch.unique(dim=0)``,
    which is several times slower on the CPU."""
    n = x.shape[0]
    order = torch.arange(n, device=x.device)
    for col in reversed(range(x.shape[1])):
        order = order[torch.argsort(x[order, col], stable=True)]
    xs = x[order]
    new = torch.ones(n, dtype=torch.bool, device=x.device)
    new[1:] = (xs[1:] != xs[:-1]).any(1)
    inverse = torch.empty(n, dtype=torch.int64, device=x.device)
    inverse[order] = torch.cumsum(new, 0) - 1
    return inverse, order[new]          # stable sorts keep equal rows in index order


def merge_vertices(position: torch.Tensor, faces: torch.Tensor, cell: float
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge vertices whose coordinates quantise to the same integers ``round(x / cell)``.

    Returns ``rep`` (V',) indices of the representatives (the lowest original index of each
    group, which keeps its exact coordinates; ordered by that index) and the faces remapped to
    rows of ``rep``. ``cell <= 0`` merges nothing. Degenerate faces are kept (§2.10)."""
    n = position.shape[0]
    if cell <= 0 or n == 0:
        return torch.arange(n, device=position.device), faces
    inv, first = unique_rows(torch.round(position / cell).to(torch.int64))
    groups = first.numel()
    order = torch.argsort(first)                 # groups by representative index
    rank = torch.empty_like(order)
    rank[order] = torch.arange(groups, device=position.device)
    return first[order], rank[inv][faces]


def compact(faces: torch.Tensor, n_vertices: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Drop unreferenced vertices: returns kept vertex indices (V',) (ascending) and remapped faces."""
    used = torch.zeros(n_vertices, dtype=torch.bool, device=faces.device)
    used[faces.reshape(-1)] = True
    keep = used.nonzero().squeeze(1)
    remap = torch.full((n_vertices,), -1, dtype=torch.int64, device=faces.device)
    remap[keep] = torch.arange(keep.numel(), device=faces.device)
    return keep, remap[faces]


def build_mesh(position: torch.Tensor, faces: torch.Tensor, metadata: dict | None = None,
               **per_vertex: torch.Tensor) -> trimesh.Trimesh | None:
    """A ``trimesh.Trimesh`` (``process=False``) from vertices (N, 3) and faces (F, 3) after
    removing unreferenced vertices; per-vertex tensors go to ``metadata`` as NumPy arrays.
    ``None`` when there is no face."""
    if faces.shape[0] == 0:
        return None
    keep, faces = compact(faces, position.shape[0])
    meta = dict(metadata or {})
    for name, arr in per_vertex.items():
        meta[name] = arr[keep].cpu().numpy()
    return trimesh.Trimesh(vertices=position[keep].cpu().numpy(), faces=faces.cpu().numpy(),
                           process=False, metadata=meta)


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
        ijk = band_leaves(field, cfg, advance)
        if ijk.shape[0] == 0:
            return None
        samples = sample_leaves(field, cfg, ijk)
        advance(1)
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
        rep, faces = merge_vertices(position, faces, 10.0 * cfg.dedup_eps)
        meta = {"extractor": "dualmesh-udf", "mode": "faithful", "leaves": int(ijk.shape[0]),
                "vertex_cells": int(cells.shape[0]), "quads": int(quads.shape[0]),
                "quads_kept": int(kept.sum())}
        mesh = build_mesh(position[rep], faces, meta, vertex_type=kind[rep],
                          vertex_direction=direction[rep])
        advance(1)
    return mesh
