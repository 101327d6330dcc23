"""Mesh-quality figures of an extracted surface (for sidecars, tests and benchmarks).

All counts are over the mesh as given (no merging): an edge is an unordered pair of distinct vertex
indices, shared by the faces that contain it.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


_DEGENERATE_REL = 1e-10  # a face is zero-area below this × (median edge length)²


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    """Connected-component labels (n,) of the graph with ``edges`` (E, 2) on n nodes."""
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def mesh_quality(mesh: trimesh.Trimesh | None) -> dict:
    """Quality figures of a triangle mesh, as plain JSON-able ints and floats.

    Keys:
        ``vertices``, ``faces``: counts.
        ``area``: total surface area (sum of triangle areas, mesh units²).
        ``components``: connected components of faces (faces sharing a vertex are connected).
        ``boundary_edges``: edges used by exactly one face.
        ``boundary_loops``: independent cycles of the boundary-edge graph (E − V + C); equals the
            number of boundary loops when loops are simple, and counts a pinched (figure-8) loop
            as two.
        ``nonmanifold_edges``: edges used by more than two faces.
        ``duplicate_faces``: faces whose vertex set repeats an earlier face (any orientation).
        ``degenerate_faces``: faces with a repeated vertex index or an area below 1e-10 × the
            squared median edge length.

    ``None`` or a mesh without faces gives zeros everywhere.
    """
    keys = ("vertices", "faces", "area", "components", "boundary_edges", "boundary_loops",
            "nonmanifold_edges", "duplicate_faces", "degenerate_faces")
    if mesh is None or len(mesh.faces) == 0:
        out = dict.fromkeys(keys, 0)
        out["area"] = 0.0
        if mesh is not None:
            out["vertices"] = int(len(mesh.vertices))
        return out
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    n = len(V)
    # Edges as sorted index pairs; pairs with equal indices (collapsed) are not edges.
    E = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    E = E[E[:, 0] != E[:, 1]]
    uniq, counts = np.unique(E, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    if len(boundary):
        nodes, local = np.unique(boundary, return_inverse=True)
        labels = _components(len(nodes), local.reshape(-1, 2))
        loops = len(boundary) - len(nodes) + int(labels.max()) + 1
    else:
        loops = 0
    used = np.unique(F)
    labels = _components(n, uniq) if len(uniq) else np.arange(n)
    components = len(np.unique(labels[used]))
    duplicates = len(F) - len(np.unique(np.sort(F, axis=1), axis=0))
    tri = V[F]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    lengths = np.linalg.norm(V[uniq[:, 0]] - V[uniq[:, 1]], axis=1) if len(uniq) else np.zeros(1)
    tiny = _DEGENERATE_REL * float(np.median(lengths)) ** 2
    repeated = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])
    return {
        "vertices": int(n),
        "faces": int(len(F)),
        "area": float(areas.sum()),
        "components": int(components),
        "boundary_edges": int(len(boundary)),
        "boundary_loops": int(loops),
        "nonmanifold_edges": int((counts > 2).sum()),
        "duplicate_faces": int(duplicates),
        "degenerate_faces": int((repeated | (areas <= tiny)).sum()),
    }


