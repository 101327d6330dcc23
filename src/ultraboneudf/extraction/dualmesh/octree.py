"""The sparse octree band of DualMesh-UDF (docs/ALGORITHMS.md §2.2–2.5): integer cell keys, adaptive
subdivision to the band of leaves around the zero set, and the leaves' field samples.

Integer cell coordinates ``ijk`` at depth ``d`` index cells of edge ``h_d = (hi − lo) / 2^d`` with
minimum corner ``lo + h_d·ijk``; all lengths in the field's own units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from ...config import ExtractConfig
from ...fields.base import Field


_MAX_BITS = 21        # 3 coordinates × 21 bits fit in a non-negative int64


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


def band_samples(field: Field, cfg: ExtractConfig, advance: Callable[[float], None] = _noop
                 ) -> tuple[torch.Tensor, LeafSamples] | None:
    """The band's leaves (:func:`band_leaves`) and their samples (:func:`sample_leaves`), the start
    of both extractors; ``None`` when no cell survives the band test."""
    ijk = band_leaves(field, cfg, advance)
    if ijk.shape[0] == 0:
        return None
    samples = sample_leaves(field, cfg, ijk)
    advance(1)
    return ijk, samples
