"""Point normals for the baselines: PCA estimation, consistent tangent-plane orientation, and the
sweep-based orientation toward the probe (§1.2 steps 4 and 6, §5.4, §7.2).

These are the UltraBoneUDF reference pipeline's normals (computed there but unused by its loss):
CarotidUDF's ``normal-sign`` conversion and Poisson need them. All inputs are unit-space arrays
(``orient_toward`` is invariant under the positive scaling of §0.1, provided points and viewpoints
went through the same map).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from .neighbors import kd_tree


def pca_normals(points: np.ndarray, cloud: np.ndarray, radius: float = 0.5, max_nn: int = 1_000,
                chunk: int = 2_000) -> np.ndarray:
    """Unit normals (N, 3) at ``points`` (N, 3): the smallest-eigenvalue eigenvector of the covariance
    of the hybrid neighbourhood in ``cloud`` (M, 3) — the ``max_nn`` nearest points within ``radius``
    (the point itself included). Sign is arbitrary; a neighbourhood of < 3 points gives +z."""
    tree = kd_tree(cloud)
    k = int(min(max_nn, len(cloud)))
    out = np.zeros((len(points), 3))
    out[:, 2] = 1.0
    for start in range(0, len(points), chunk):
        dist, idx = tree.query(points[start:start + chunk], k=k, distance_upper_bound=radius, workers=-1)
        dist, idx = dist.reshape(len(dist), k), idx.reshape(len(idx), k)
        valid = np.isfinite(dist)
        nb = cloud[np.minimum(idx, len(cloud) - 1)]                   # (C, k, 3); invalid rows masked
        w = valid[..., None].astype(float)
        count = w.sum(axis=1)                                         # (C, 1)
        mean = (nb * w).sum(axis=1) / np.maximum(count, 1.0)
        centred = (nb - mean[:, None]) * w
        cov = np.einsum("cki,ckj->cij", centred, centred)
        _, vecs = np.linalg.eigh(cov)                                 # ascending eigenvalues
        normals = vecs[:, :, 0]
        ok = count[:, 0] >= 3
        out[start:start + chunk][ok] = normals[ok]
    return out


def orient_tangent_plane(points: np.ndarray, normals: np.ndarray, k: int = 15) -> np.ndarray:
    """Consistently oriented copy of ``normals`` (N, 3) by tangent-plane propagation [I: Hoppe-style,
    as the Open3D call of §1.2 step 6]: a minimum spanning tree of the ``k``-NN graph with edge cost
    ``1 − |n_i·n_j|`` is walked breadth-first and each child is flipped to agree with its parent.
    Each connected component starts at its highest point (largest z) with its normal turned to +z.
    Orientation can fail across gaps between slices; that is the baseline's behaviour (§5.6)."""
    n = len(points)
    out = normals.copy()
    if n < 2:
        return out
    kk = int(min(k + 1, n))
    _, idx = kd_tree(points).query(points, k=kk, workers=-1)
    rows = np.repeat(np.arange(n), kk - 1)
    cols = idx[:, 1:].reshape(-1)
    # + 1e-6: zero-cost edges (parallel normals) must stay edges for the sparse graph
    cost = 1.0 - np.abs((normals[rows] * normals[cols]).sum(axis=1)) + 1e-6
    graph = coo_matrix((cost, (rows, cols)), shape=(n, n)).tocsr()
    graph = graph.maximum(graph.T)
    tree = minimum_spanning_tree(graph)
    tree = tree + tree.T
    n_comp, label = connected_components(tree, directed=False)
    for c in range(n_comp):
        members = np.flatnonzero(label == c)
        root = int(members[np.argmax(points[members, 2])])
        if out[root, 2] < 0:
            out[root] = -out[root]
        order, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
        for node in order[1:]:
            if np.dot(out[node], out[pred[node]]) < 0:
                out[node] = -out[node]
    return out


def orient_toward(points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray) -> np.ndarray:
    """Flip each normal to face its ``viewpoints`` row (N, 3) — for a sweep, the probe position of
    the frame the point came from (§7.2 alternative B): the imaged bone surface faces the transducer."""
    facing = ((viewpoints - points) * normals).sum(axis=1) >= 0
    return np.where(facing[:, None], normals, -normals)


def ultraboneudf_normals(surface: np.ndarray, cloud: np.ndarray, radius: float = 0.5, max_nn: int = 1_000,
                         k_orient: int = 15) -> np.ndarray:
    """The reference pipeline's oriented normals of the surface rows (§1.2 steps 4 and 6): PCA on the
    whole normalised ``cloud`` (radius 0.5, ≤ 1,000 neighbours), then orientation over ``surface``."""
    return orient_tangent_plane(surface, pca_normals(surface, cloud, radius, max_nn), k_orient)
