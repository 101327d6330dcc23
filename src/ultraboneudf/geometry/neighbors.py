"""Exact nearest neighbours: the one implementation of the package (§0.4), for training, the point
stages, extraction and evaluation.

- :func:`kd_tree`: a SciPy KD-tree over a point set, the CPU back-end of everything below and what
  modules that need more than the nearest point (k nearest, balls) query directly.
- :class:`NearestIndex`: the nearest point's index, queried with tensors on the training device: the
  KD-tree on the CPU, chunked brute force with a running argmin on a GPU (the ``K × N`` distance
  matrix is never materialised whole).
- :func:`nearest_distances`: distances between large point sets (mm, the evaluation's 5e6 × 5e6
  samples): on the CPU a KD-tree tuned for surface samples (:func:`surface_tree`) searched in
  Morton (Z-curve) order, which keeps neighbouring queries on neighbouring memory and roughly halves
  the query time; on a torch device (CUDA) a uniform-grid search: reference points are bucketed
  into cubic cells of edge ``h`` and a query compared with every point in the 3×3×3 cells around
  its own. A found distance ``≤ h`` is exact, since every point outside that block is at least ``h``
  away; queries with no such neighbour are searched again with ``2h`` until all are resolved. The
  two back-ends give the same numbers up to float32 rounding on the GPU (below 1e-4 mm for
  coordinates of a few hundred mm).

Distances are Euclidean, not squared. PyTorch is imported only where a tensor is used, so the
evaluation runs without loading it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    import torch

KDTree = cKDTree
"""The KD-tree type :func:`kd_tree` and :func:`surface_tree` return."""


def kd_tree(points: np.ndarray) -> KDTree:
    """A KD-tree over ``(N, 3)`` points with SciPy's default parameters; query it with
    ``workers=-1`` for all cores (``query``, ``query_ball_point``, …)."""
    return cKDTree(points)


def knn_distance(points: np.ndarray, k: int) -> np.ndarray:
    """Distance ``(N,)`` from each point to its k-th nearest *other* point (the (k+1)-th result of a
    query that returns the point itself first). Duplicated rows count as neighbours at distance 0
    (§0.7). ``k`` is clipped to ``N − 1``."""
    k = min(int(k), len(points) - 1)
    dist, _ = kd_tree(points).query(points, k=k + 1, workers=-1)
    return dist[:, k]


SMALL_QUERY = 4_096
"""Below this many query points the KD-tree is searched on one thread."""


def brute_force_nearest(x: torch.Tensor, points: torch.Tensor, chunk: int = 2048,
                        points_sq: torch.Tensor | None = None) -> torch.Tensor:
    """Index ``(M,)`` of the nearest row of ``points`` (N, 3) for every row of ``x`` (M, 3), on their
    device, without a graph: chunks of ``chunk`` rows against all of ``points`` (the ``M × N``
    distance matrix is never whole), ties towards the lowest index. ``points_sq``: the rows' squared
    norms, when the caller keeps them."""
    import torch

    out = []
    with torch.no_grad():
        sq = points.square().sum(dim=1) if points_sq is None else points_sq
        for xc in x.detach().split(chunk):
            # |x − p|² = |x|² − 2 x·p + |p|²; |x|² is constant per row and does not change the argmin.
            out.append(torch.addmm(sq, xc, points.T, beta=1.0, alpha=-2.0).argmin(dim=1))
    return torch.cat(out)


class NearestIndex:
    """Exact nearest-neighbour index over fixed points ``P`` (N, 3), queried with tensors.

    ``query(x)`` returns the ``(M,)`` long tensor of indices into ``P`` on ``x``'s device. Ties are
    broken towards the lowest index on the GPU path (strict ``<`` over chunks); the KD-tree returns
    an exact nearest point whose tie order is the tree's.
    """

    def __init__(self, points: torch.Tensor, chunk: int = 2048) -> None:
        self.points = points
        self.chunk = chunk
        self.on_cpu = points.device.type == "cpu"
        if self.on_cpu:
            self._tree = kd_tree(points.detach().double().numpy())
        else:
            self._sq = points.square().sum(dim=1)

    def query(self, x: torch.Tensor) -> torch.Tensor:
        import torch

        if self.on_cpu:
            # A worker pool costs more than it saves on a small batch (measured: 250 queries 0.93 ms
            # with all cores, 0.63 ms with one).
            workers = 1 if len(x) < SMALL_QUERY else -1
            _, idx = self._tree.query(x.detach().double().numpy(), k=1, workers=workers)
            return torch.from_numpy(np.asarray(idx, dtype=np.int64))
        return brute_force_nearest(x, self.points, self.chunk, self._sq)


_MORTON_BITS = 10
_SPREAD = np.zeros(1 << _MORTON_BITS, dtype=np.uint64)
for _i in range(1 << _MORTON_BITS):
    _v = 0
    for _b in range(_MORTON_BITS):
        _v |= ((_i >> _b) & 1) << (3 * _b)
    _SPREAD[_i] = _v
del _i, _v, _b


def morton_order(points: np.ndarray) -> np.ndarray:
    """Permutation ``(N,)`` that sorts ``(N, 3)`` points along a 3-D Z-curve of 2^30 cells."""
    lo = points.min(axis=0)
    span = float((points.max(axis=0) - lo).max())
    scale = ((1 << _MORTON_BITS) - 1) / span if span > 0 else 0.0
    q = np.clip((points - lo) * scale, 0, (1 << _MORTON_BITS) - 1).astype(np.intp)
    code = _SPREAD[q[:, 0]] | (_SPREAD[q[:, 1]] << np.uint64(1)) | (_SPREAD[q[:, 2]] << np.uint64(2))
    return np.argsort(code, kind="stable")


def spatially_sorted(points: np.ndarray) -> np.ndarray:
    """A C-contiguous float64 copy of ``points`` in Morton order."""
    points = np.asarray(points, dtype=np.float64)
    return np.ascontiguousarray(points[morton_order(points)])


def surface_tree(points: np.ndarray) -> KDTree:
    """A KD-tree over ``(N, 3)`` points, tuned for surface samples.

    Leaf size 32, sliding-midpoint splits (``balanced_tree=False``) and cells not shrunk to the
    data (``compact_nodes=False``): on the 5e6 × 5e6 femur samples of ``benchmarks/bench_evaluate.py``
    this builds in half the time and queries 2.5× faster than the defaults (docs/evaluation.md).
    """
    return cKDTree(np.asarray(points, dtype=np.float64), leafsize=32, compact_nodes=False,
                   balanced_tree=False)


def tree_distances(tree: KDTree, query: np.ndarray, workers: int = -1,
                   presorted: bool = False, advance: Callable[[float], None] | None = None) -> np.ndarray:
    """Distance (mm) from each query row to its nearest point in ``tree``; ``(M,)`` float64.

    Queries are searched in Morton order (skipped when ``presorted``, e.g. the output of
    :func:`spatially_sorted`) and the result returned in the caller's order. ``advance(n)``, if
    given, is told of the rows done, a twentieth at a time (a progress stage of ``M`` steps).
    """
    query = np.asarray(query, dtype=np.float64)
    if len(query) == 0:
        return np.zeros(0, dtype=np.float64)
    order = None if presorted else morton_order(query)
    rows = query if order is None else query[order]
    if advance is None:
        d_sorted = tree.query(rows, k=1, workers=workers)[0]
    else:
        d_sorted = np.empty(len(rows), dtype=np.float64)
        step = max(100_000, -(-len(rows) // 20))
        for s in range(0, len(rows), step):
            chunk = rows[s:s + step]
            d_sorted[s:s + len(chunk)] = tree.query(chunk, k=1, workers=workers)[0]
            advance(len(chunk))
    if order is None:
        return d_sorted
    out = np.empty(len(query), dtype=np.float64)
    out[order] = d_sorted
    return out


def nearest_distances(query: np.ndarray, reference: np.ndarray, workers: int = -1,
                      device: str = "cpu") -> np.ndarray:
    """For every row of ``query`` (M, 3), the distance (mm) to the nearest row of ``reference`` (N, 3).

    ``device="cpu"`` uses the KD-tree; any other torch device (``"cuda"``, ``"cuda:1"``) the grid
    search. Returns ``(M,)`` float64; raises ``ValueError`` if ``reference`` is empty.
    """
    reference = np.asarray(reference, dtype=np.float64)
    if len(reference) == 0:
        raise ValueError("nearest_distances: the reference set is empty")
    if device == "cpu":
        return tree_distances(surface_tree(reference), query, workers=workers)
    return grid_distances(query, reference, device=device)


# --------------------------------------------------------------------------------------------
# uniform-grid search in torch (for CUDA; runs on any torch device)


def _np_cell_keys(cells: np.ndarray, dim: int) -> np.ndarray:
    """Linear key of integer cell coordinates ``(M, 3)`` in a box of ``dim`` cells per axis."""
    return (cells[:, 0] * dim + cells[:, 1]) * dim + cells[:, 2]


def _grid_cell_size(ref, target_per_cell: float = 6.0) -> float:
    """Cell edge (mm) that puts about ``target_per_cell`` reference points in an occupied cell."""
    import torch

    lo = ref.min(dim=0).values
    extent = float((ref.max(dim=0).values - lo).max())
    if extent <= 0:
        return 1.0
    c0 = extent / 256.0
    occupied = int(torch.unique(_cell_keys(torch.floor((ref - lo) / c0).long(), 258)).numel())
    return max(c0 * (target_per_cell * occupied / len(ref)) ** 0.5, extent * 1e-6)


def _cell_keys(cells, dim: int):
    """Linear key of integer cell coordinates ``(M, 3)`` in a box of ``dim`` cells per axis."""
    return (cells[:, 0] * dim + cells[:, 1]) * dim + cells[:, 2]


def grid_distances(query: np.ndarray, reference: np.ndarray, device: str = "cuda",
                   chunk: int = 1 << 21, max_doublings: int = 2, workers: int = -1) -> np.ndarray:
    """Exact nearest-neighbour distances by uniform-grid search on a torch ``device``; ``(M,)`` float64.

    Coordinates are shifted to a common origin and searched in float32. Queries still unresolved
    after ``max_doublings`` doublings of the cell (points far from every reference point, where a
    grid degenerates into brute force) are answered by the CPU KD-tree.
    """
    import torch

    dev = torch.device(device)
    q_np = np.asarray(query, dtype=np.float64)
    r_np = np.asarray(reference, dtype=np.float64)
    if len(q_np) == 0:
        return np.zeros(0, dtype=np.float64)
    origin = np.minimum(q_np.min(axis=0), r_np.min(axis=0))
    q = torch.as_tensor(q_np - origin, dtype=torch.float32, device=dev)
    r = torch.as_tensor(r_np - origin, dtype=torch.float32, device=dev)
    extent = float(max(q.max(), r.max())) + 1e-6
    best = torch.full((len(q),), float("inf"), dtype=torch.float32, device=dev)
    pending = torch.arange(len(q), device=dev)
    cell = _grid_cell_size(r)
    offsets = torch.tensor([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                           dtype=torch.long, device=dev)
    for level in range(max_doublings + 1):
        if len(pending) == 0:
            break
        dim = int(extent / cell) + 3  # cells per axis, with a margin of one on each side
        keys, order = torch.sort(_cell_keys(torch.floor(r / cell).long() + 1, dim))
        r_sorted = r[order]
        uniq, counts = torch.unique_consecutive(keys, return_counts=True)
        starts = torch.cumsum(counts, 0) - counts
        q_cells = torch.floor(q[pending] / cell).long() + 1
        q_order = torch.argsort(_cell_keys(q_cells, dim))  # neighbouring queries, coherent gathers
        pending, q_cells = pending[q_order], q_cells[q_order]
        found = torch.empty(len(pending), dtype=torch.float32, device=dev)
        for a in range(0, len(pending), chunk):
            b = min(len(pending), a + chunk)
            qc, qp = q_cells[a:b], q[pending[a:b]]
            local = torch.full((b - a,), float("inf"), dtype=torch.float32, device=dev)
            for off in offsets:
                nk = _cell_keys(qc + off, dim)
                pos = torch.searchsorted(uniq, nk).clamp_(max=len(uniq) - 1)
                cnt = torch.where(uniq[pos] == nk, counts[pos], torch.zeros_like(pos))
                st = starts[pos]
                for j in range(int(cnt.max())):
                    valid = cnt > j
                    d2 = ((qp - r_sorted[torch.where(valid, st + j, 0)]) ** 2).sum(dim=1)
                    local = torch.minimum(local, d2.masked_fill_(~valid, float("inf")))
            found[a:b] = local
        # exact where the nearest point found lies within one cell (all others are ≥ one cell away)
        done = found <= cell * cell
        best[pending[done]] = found[done]
        pending = pending[~done]
        cell *= 2.0
    out = torch.sqrt(best).double().cpu().numpy()
    if len(pending):
        rest = pending.cpu().numpy()
        out[rest] = tree_distances(surface_tree(r_np), q_np[rest], workers=workers)
    return out
