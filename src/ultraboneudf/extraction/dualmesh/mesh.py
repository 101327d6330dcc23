"""Dual quads over the octree band and the mesh's assembly (docs/ALGORITHMS.md §2.8, §2.10): the
four cells around a lattice edge, vertex merging, compaction."""

from __future__ import annotations

import torch
import trimesh

from .octree import pack


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
    """Merge vertices whose coordinates quantise to the same integers ``round(x / cell)`` (halves
    rounded away from zero, as libigl's ``round``).

    Returns ``rep`` (V',) indices of the representatives (the lowest original index of each
    group, which keeps its exact coordinates; ordered by that index) and the faces remapped to
    rows of ``rep``. ``cell <= 0`` merges nothing. Degenerate faces are kept (§2.10)."""
    n = position.shape[0]
    if cell <= 0 or n == 0:
        return torch.arange(n, device=position.device), faces
    scaled = position / cell
    inv, first = unique_rows((torch.sign(scaled) * torch.floor(scaled.abs() + 0.5)).to(torch.int64))
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
