"""DualMesh-UDF mesh extraction (docs/ALGORITHMS.md §2), vectorised in torch over a sparse octree band.

The reference (DMU, C++) walks an octree; here every stage is a batched tensor operation on the
cells that survive subdivision (§2.12): int64 cell keys, one batched field query per level, the
``L × K`` leaf samples (``K = (2^s + 1)³ = 27``) uniqued and evaluated once, a batched per-leaf
QEF in float64, dual quads by ``searchsorted`` on sorted keys and the triangulation rules of §2.9
as boolean algebra. Nothing is indexed by the full lattice, so memory follows the band size.
Coordinates, sizes and thresholds are in the field's own units (unit space in the pipeline, §0.1).

- :mod:`.octree`: integer cell keys, the band of leaves (§2.3), the leaves' samples (§2.4–2.5);
- :mod:`.qef`: the per-leaf vertex (§2.6);
- :mod:`.mesh`: dual quads (§2.8), vertex merging and the mesh's assembly (§2.10);
- :mod:`.faithful`: the extractor as the reference runs it (``extract.mode = faithful``);
- :mod:`.edge_crossing`: one quad per lattice edge the surface crosses, a one-layer mesh with
  manifold edges, on the same band, samples and vertices (``extract.mode = clean``).
"""

from .edge_crossing import clean_udf_mesh
from .faithful import dualmesh_udf, triangulate_dmu
from .mesh import build_mesh, cell_ring, dual_quads, merge_vertices
from .octree import Lattice, band_leaves, band_samples, band_threshold, pack, sample_leaves, unpack
from .qef import CORNER, EDGE, NO_VERTEX, PLANE, TYPE_NAMES, qef_solve, solve_leaves

__all__ = ["CORNER", "EDGE", "NO_VERTEX", "PLANE", "TYPE_NAMES", "Lattice", "band_leaves", "band_samples",
           "band_threshold", "build_mesh", "cell_ring", "clean_udf_mesh", "dual_quads", "dualmesh_udf",
           "merge_vertices", "pack", "qef_solve", "sample_leaves", "solve_leaves", "triangulate_dmu", "unpack"]
