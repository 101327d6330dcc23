"""DualMesh-UDF, faithful mode (docs/ALGORITHMS.md §2, Appendix C), on exact analytic UDFs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ultraboneudf.config import DMU_DEFAULTS, ExtractConfig
from ultraboneudf.errors import InputError
from ultraboneudf.extraction import CORNER, EDGE, PLANE, band_threshold, dualmesh_udf, extract_mesh
from ultraboneudf.extraction import dualmesh as dm
from ultraboneudf.fields import DiscUDF, Field, PlaneUDF, SphereUDF, TorusUDF
from ultraboneudf.progress import Progress

UBU = ExtractConfig                       # the UltraBoneUDF call (§1.8) is the dataclass default


def dmu(**kw) -> ExtractConfig:
    """The official DualMesh-UDF driver values (§2.11)."""
    return ExtractConfig(**{**DMU_DEFAULTS, **kw})


class ConstantField(Field):
    """u ≡ c with a zero gradient everywhere."""

    def __init__(self, c: float):
        self.c = c

    def _value(self, x):
        return torch.full((x.shape[0],), self.c, dtype=x.dtype, device=x.device)

    def _value_and_grad(self, x):
        return self._value(x), torch.zeros_like(x)


class HalfNaNSphere(SphereUDF):
    """The sphere UDF with NaN values and gradients in the half-space x > 0."""

    def _value_and_grad(self, x):
        u, g = super()._value_and_grad(x)
        bad = x[:, 0] > 0
        return torch.where(bad, float("nan"), u), torch.where(bad[:, None], float("nan"), g)


def canonical(mesh) -> np.ndarray:
    """Order-independent form of a mesh: its faces as sorted triples of vertex coordinates, sorted."""
    tri = np.round(mesh.vertices[mesh.faces], 12)
    tri = np.sort(tri.view([("x", float), ("y", float), ("z", float)]).reshape(len(tri), 3), axis=1)
    return np.sort(tri.view(float).reshape(len(tri), 9), axis=0)


# ------------------------------------------------------------------------------------ geometry

def test_band_threshold_and_leaf_edge_at_depth_9():
    cfg = UBU(max_depth=9)
    assert dm.Lattice.from_config(cfg).cell_size() == pytest.approx(1 / 256)
    assert band_threshold(9, cfg) == pytest.approx(0.00538, abs=5e-6)
    assert band_threshold(9, cfg) == pytest.approx(math.sqrt(3) / 2 / 256 + 0.002)


def test_pack_unpack_roundtrip():
    ijk = torch.tensor([[0, 0, 0], [1023, 5, 1024], [7, 1024, 3]])
    assert torch.equal(dm.unpack(dm.pack(ijk, 11), 11), ijk)


def test_band_leaves_contain_every_cell_the_sphere_passes_through():
    cfg = UBU(max_depth=5)
    leaves = dm.band_leaves(SphereUDF(0.3), cfg)
    lo, hi = dm.Lattice.from_config(cfg).leaf_boxes(leaves)
    # Exact UDF: every leaf touching the sphere passes the half-diagonal test; check a dense set
    # of sphere points lands in some leaf.
    g = torch.randn(2000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    pts = 0.3 * g / g.norm(dim=1, keepdim=True)
    covered = ((pts[:, None] >= lo[None]) & (pts[:, None] <= hi[None])).all(2).any(1)
    assert bool(covered.all())
    # Sorted, unique keys.
    keys = dm.pack(leaves, 6)
    assert torch.equal(keys, torch.unique(keys))


class _FarOverestimate(SphereUDF):
    """The sphere's UDF d up to 0.2, then 0.2 + 3·(d − 0.2): right near the surface, three times too
    large far away, as a trained field can be where no query constrained it."""

    def _value_and_grad(self, x):
        d, g = super()._value_and_grad(x)
        far = d > 0.2
        return torch.where(far, 0.2 + 3 * (d - 0.2), d), torch.where(far[:, None], 3 * g, g)


def test_band_start_depth_keeps_octants_an_overestimating_field_would_lose():
    """At depth 1 every octant centre (±0.5)³ is 0.566 from the sphere of radius 0.3, the field says
    1.30 > 0.868 (the half-diagonal): the reference test drops all eight octants and the sphere.
    Testing from depth 3 (cells 0.25, centres near the sphere within 0.2 of it) keeps every leaf the
    sphere passes through."""
    field = _FarOverestimate(0.3)
    assert dm.band_leaves(field, UBU(max_depth=5)).shape[0] == 0
    cfg = UBU(max_depth=5, band_start_depth=3)
    leaves = dm.band_leaves(field, cfg)
    assert torch.equal(leaves, dm.band_leaves(SphereUDF(0.3), cfg))
    assert torch.equal(leaves, dm.band_leaves(SphereUDF(0.3), UBU(max_depth=5)))


# ------------------------------------------------------------------------------------ the QEF

def _solve(planes, lo=(-0.5, -0.5, -0.5), hi=(0.5, 0.5, 0.5), **kw):
    """SOLVE on explicit tangent planes n·y = b (unit normals), one cell."""
    n = torch.tensor([p[0] for p in planes], dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    b = torch.tensor([p[1] for p in planes], dtype=torch.float64)
    M, r = (n.T @ n)[None], (n.T @ b)[None]
    lo, hi = torch.tensor([lo], dtype=torch.float64), torch.tensor([hi], dtype=torch.float64)
    return dm.qef_solve(M, r, lo, hi, UBU(**kw))


def test_qef_ranks_corner_edge_plane():
    corner = _solve([((1, 0, 0), 0.1), ((0, 1, 0), 0.2), ((0, 0, 1), -0.3)] * 2)
    assert bool(corner.ok) and int(corner.kind) == CORNER
    assert torch.allclose(corner.position[0], torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64))
    edge = _solve([((1, 0, 0), 0.1), ((0, 1, 0), 0.2)] * 3)
    assert bool(edge.ok) and int(edge.kind) == EDGE
    assert abs(float(edge.direction[0, 2])) == pytest.approx(1.0)
    # The chord of the line x = 0.1, y = 0.2 through the cell: midpoint at z = 0.
    assert torch.allclose(edge.position[0], torch.tensor([0.1, 0.2, 0.0], dtype=torch.float64))
    plane = _solve([((0, 0, 1), 0.25)] * 4)
    assert bool(plane.ok) and int(plane.kind) == PLANE
    assert torch.allclose(plane.position[0], torch.tensor([0.0, 0.0, 0.25], dtype=torch.float64))


def test_qef_rejects_zero_and_nan_systems():
    zero = dm.qef_solve(torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                        -torch.ones(1, 3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64), UBU())
    assert not bool(zero.ok)                       # σ_1 = 0 → no vertex
    M = torch.eye(3, dtype=torch.float64)[None].clone()
    M[0, 0, 0] = float("nan")
    nan = dm.qef_solve(M, torch.zeros(1, 3, dtype=torch.float64),
                       -torch.ones(1, 3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64), UBU())
    assert not bool(nan.ok)


def test_plane_acceptance_window():
    # Plane z = 0.9 misses the cell [−0.5, 0.5]³ by 0.4 cells: accepted with f_p = 1, not with 0.15.
    assert bool(_solve([((0, 0, 1), 0.9)] * 3, plane_factor=1.0).ok)
    assert not bool(_solve([((0, 0, 1), 0.9)] * 3, plane_factor=0.15).ok)


# ------------------------------------------------------------------------------------ §2.9 rules

def _quad(points, kinds, dirs):
    P = torch.tensor(points, dtype=torch.float64)
    return dm.triangulate_dmu(P, torch.tensor(kinds, dtype=torch.int8), torch.tensor(dirs, dtype=torch.float64),
                              torch.arange(4)[None])


def test_triangulation_rules():
    square = [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)]
    ez, ex = (0, 0, 1), (1, 0, 0)
    faces, keep = _quad(square, [PLANE] * 4, [ez] * 4)
    assert bool(keep[0]) and faces.tolist() == [[0, 1, 2], [2, 3, 0]]
    faces, keep = _quad(square, [PLANE, PLANE, PLANE, PLANE], [ez, ez, (0.7071, 0, 0.7071), ez])
    assert not bool(keep[0])                              # a plane normal 45° off the quad normal
    faces, keep = _quad(square, [EDGE, PLANE, PLANE, PLANE], [ez, ez, ez, ez])
    assert not bool(keep[0])                              # a crease line across the quad plane
    faces, keep = _quad(square, [EDGE, PLANE, PLANE, PLANE], [ex, ez, ez, ez])
    assert bool(keep[0])                                  # a crease line lying in the quad plane
    # Non-coplanar (a saddle), PLANE vertices 1 and 3 with normals of their own triangles.
    saddle = torch.tensor([(0, 0, 0), (0, 1, 1), (1, 1, 0), (1, 0, 1)], dtype=torch.float64)
    n1 = torch.linalg.cross(saddle[2] - saddle[1], saddle[0] - saddle[1])
    n3 = torch.linalg.cross(saddle[0] - saddle[3], saddle[2] - saddle[3])
    dirs = [ex, (n1 / n1.norm()).tolist(), ex, (n3 / n3.norm()).tolist()]
    faces, keep = _quad(saddle.tolist(), [CORNER, PLANE, CORNER, PLANE], dirs)
    assert bool(keep[0]) and faces.tolist() == [[3, 0, 2], [0, 1, 2]]   # t = 3
    faces, keep = _quad(saddle.tolist(), [CORNER, PLANE, PLANE, CORNER], [ex, dirs[1], dirs[1], ex])
    assert not bool(keep[0])                              # adjacent PLANE vertices are invalid
    faces, keep = _quad(saddle.tolist(), [EDGE, CORNER, EDGE, CORNER], [ex] * 4)
    assert faces.tolist() == [[0, 1, 2], [2, 3, 0]]
    faces, keep = _quad(saddle.tolist(), [CORNER] * 4, [ex] * 4)
    assert faces.tolist() == [[0, 1, 3], [1, 2, 3]]


# ------------------------------------------------------------------------------------ whole extractor

@pytest.mark.parametrize("cfg, layers", [(UBU(max_depth=7), 2), (dmu(max_depth=7), 1)],
                         ids=["ubu", "dmu"])
def test_plane_vertices_are_plane_type_on_the_plane(cfg, layers):
    z0 = 0.1
    mesh = dualmesh_udf(PlaneUDF(offset=z0), cfg)
    assert mesh is not None and len(mesh.faces) > 0
    kind, direction = mesh.metadata["vertex_type"], mesh.metadata["vertex_direction"]
    assert np.all(kind == PLANE)
    assert np.allclose(np.abs(direction[:, 2]), 1.0, atol=1e-9)
    assert np.abs(mesh.vertices[:, 2] - z0).max() < 1e-12
    # z0 lies 0.4 cell into a leaf: two band layers; with f_p = 1.0 both own (coincident)
    # vertices, with 0.15 only the layer containing the plane (Appendix C).
    assert mesh.metadata["leaves"] == 2 * 128 * 128
    assert mesh.metadata["vertex_cells"] == layers * 128 * 128


@pytest.mark.parametrize("cfg", [UBU(max_depth=7), dmu(max_depth=7)], ids=["ubu-d7", "dmu-d7"])
def test_sphere_vertices_are_close_to_the_sphere(cfg):
    mesh = dualmesh_udf(SphereUDF(0.3), cfg)
    assert mesh is not None
    h = 2.0 / 2 ** cfg.max_depth
    radial = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3)
    assert radial.max() < 0.1 * h                     # ≪ one leaf cell
    assert np.isfinite(mesh.vertices).all()
    assert mesh.faces.max() < len(mesh.vertices)


def test_ubu_and_dmu_parameters_give_different_meshes():
    ubu, official = dualmesh_udf(SphereUDF(0.3), UBU(max_depth=7)), dualmesh_udf(SphereUDF(0.3), dmu(max_depth=7))
    assert ubu is not None and official is not None
    # f_p = 1.0 accepts vertices of off-surface band cells: more vertices, more (stacked) area.
    assert len(ubu.vertices) > len(official.vertices)
    assert ubu.area > official.area > 0.9 * 4 * math.pi * 0.09


def test_sphere_depth_9_ubu_call():
    # Appendix C at the depth of the UltraBoneUDF call (about 11 s on one CPU thread).
    mesh = dualmesh_udf(SphereUDF(0.3), UBU(max_depth=9))
    radial = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3)
    assert radial.max() < 0.1 / 256


class DriverPrecision(Field):
    """A float64 field evaluated the way the reference's Python driver feeds its C++ core: the
    query points rounded to float32, the values and gradients returned as float32."""

    def __init__(self, inner: Field):
        self.inner = inner

    def _value_and_grad(self, x):
        u, g = self.inner._value_and_grad(x.to(torch.float32).to(torch.float64))
        return u.to(torch.float32), g.to(torch.float32)

    def _value(self, x):
        return self._value_and_grad(x)[0]


# (vertices, faces) of the unmodified reference (cong-yi/DualMesh-UDF at 0e0ace1, its C++ core
# driven like DualMeshUDF/extract_mesh.py, libigl 2.6's remove_duplicate_vertices) on the same
# float32 field values: the driver's parameter set at depth 7, the UltraBoneUDF call's at depth 8.
REFERENCE_COUNTS = [
    ("disc", lambda: DiscUDF(0.4), dmu(max_depth=7), (2392, 16388)),
    ("disc", lambda: DiscUDF(0.4), UBU(max_depth=8), (9088, 66452)),
    ("sphere", lambda: SphereUDF(0.3), dmu(max_depth=7), (8360, 21900)),
    ("torus", lambda: TorusUDF(0.4, 0.1), dmu(max_depth=7), (10832, 27144)),
    ("plane", lambda: PlaneUDF(offset=0.1), dmu(max_depth=7), (16384, 32258)),
]


@pytest.mark.parametrize("make, cfg, counts", [c[1:] for c in REFERENCE_COUNTS],
                         ids=[f"{c[0]}-{'dmu' if c[2].dedup_eps == 1e-7 else 'ubu'}-d{c[2].max_depth}"
                              for c in REFERENCE_COUNTS])
def test_vertex_and_face_counts_equal_the_reference(make, cfg, counts):
    # The disc lies on a lattice plane: both band layers own vertices at the same places, the
    # quads between the layers join coincident pairs (collinear points), and the reference keeps
    # them as its SVD's column order dictates; its duplicate merge then leaves one sheet of
    # vertices with every face twice.
    mesh = dualmesh_udf(DriverPrecision(make()), cfg)
    assert (len(mesh.vertices), len(mesh.faces)) == counts


@pytest.mark.parametrize("field", [PlaneUDF(offset=5.0), ConstantField(1.0), ConstantField(float("nan"))],
                         ids=["plane-outside", "constant-1", "nan"])
def test_no_surface_gives_none(field):
    assert dualmesh_udf(field, UBU(max_depth=7)) is None


def test_zero_field_with_zero_gradients_gives_none():
    # Every cell survives (u = 0), but no sample is usable (u ≤ τ_min, zero gradient): no vertex.
    assert dualmesh_udf(ConstantField(0.0), UBU(max_depth=4)) is None


def test_nan_region_is_rejected_not_propagated():
    mesh = dualmesh_udf(HalfNaNSphere(0.3), UBU(max_depth=6))
    assert mesh is not None
    assert np.isfinite(mesh.vertices).all()
    assert mesh.vertices[:, 0].max() < 2.0 / 64 * 1.5   # nothing deep inside the NaN half


def test_deterministic_and_independent_of_batch_size():
    a = dualmesh_udf(SphereUDF(0.3, centre=(0.01, -0.02, 0.03)), UBU(max_depth=6))
    b = dualmesh_udf(SphereUDF(0.3, centre=(0.01, -0.02, 0.03)), UBU(max_depth=6, batch=777))
    assert len(a.faces) == len(b.faces)
    assert np.array_equal(canonical(a), canonical(b))


def test_dispatcher_and_progress():
    field, cfg = SphereUDF(0.3), UBU(max_depth=5)
    a = extract_mesh(field, cfg, Progress(quiet=False))
    b = dualmesh_udf(field, cfg)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    with pytest.raises(InputError):
        extract_mesh(field, UBU(max_depth=5, mode="bogus"))


def test_shifted_domain():
    # A domain other than [−1, 1]³ works and keeps the vertices on the surface.
    cfg = UBU(max_depth=6, domain=(-0.5, 0.5))
    mesh = dualmesh_udf(SphereUDF(0.3), cfg)
    radial = np.abs(np.linalg.norm(mesh.vertices, axis=1) - 0.3)
    assert radial.max() < 0.1 * (1.0 / 64)


def _vertex_gap(a, b) -> float:
    """Largest distance from a vertex of either mesh to the nearest vertex of the other."""
    from scipy.spatial import cKDTree

    return max(cKDTree(a.vertices).query(b.vertices)[0].max(), cKDTree(b.vertices).query(a.vertices)[0].max())


# Vertices of the same field extracted on two devices agree to this fraction of the leaf edge. Both
# compute in float64, but their kernels round differently: CUDA's reductions and batched matrix
# products sum in another order, and its batched eigen-solver is another algorithm than LAPACK's,
# so field values, gradients and the QEF's normal equations differ in the last bits (~1e-16
# relative). The vertex solve is well conditioned at that scale: a relative error δ of the field
# moves the vertices by about 2δ leaf edges (measured below), so rounding moves them ~1e-16 of a
# leaf; 1e-6 leaves a wide margin for the devices' other kernels and is still far below any
# geometric difference.
DEVICE_TOLERANCE = 1e-6


class RoundedSphere(SphereUDF):
    """The sphere UDF with its values and gradients off by a relative ``rel`` (a rounding error
    larger than float64's), varying from sample to sample."""

    def __init__(self, rel: float):
        super().__init__(0.3)
        self.rel = rel

    def _value_and_grad(self, x):
        u, g = super()._value_and_grad(x)
        n1 = torch.sin(1e4 * (x @ torch.tensor([1.0, 1.7, 2.3], dtype=x.dtype)))
        n2 = torch.cos(1e4 * (x @ torch.tensor([2.9, 0.3, 1.1], dtype=x.dtype)))
        return u * (1 + self.rel * n1), g * (1 + self.rel * n2[:, None]) + self.rel * n1[:, None]

    def _value(self, x):
        return self._value_and_grad(x)[0]


def test_rounding_errors_of_the_field_move_the_vertices_far_less_than_the_device_tolerance():
    cfg = UBU(max_depth=6)
    exact = dualmesh_udf(SphereUDF(0.3), cfg)
    rounded = dualmesh_udf(RoundedSphere(1e-12), cfg)   # 10,000 times float64's rounding
    assert len(rounded.vertices) == len(exact.vertices) and len(rounded.faces) == len(exact.faces)
    assert _vertex_gap(exact, rounded) < 1e-10 * (2.0 / 2 ** 6) < DEVICE_TOLERANCE * (2.0 / 2 ** 6)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    """Same counts, and every vertex within :data:`DEVICE_TOLERANCE` leaf edges of one of the other
    device's. Matched to the nearest vertex, not compared in sorted order: the sphere's mirror-image
    vertices share their x coordinate to the bit on one device and not on the other, which reorders
    a lexicographic sort."""
    cfg = UBU(max_depth=7)
    cpu = dualmesh_udf(SphereUDF(0.3), cfg)
    gpu = dualmesh_udf(SphereUDF(0.3, device="cuda"), cfg)
    assert len(gpu.faces) == len(cpu.faces) and len(gpu.vertices) == len(cpu.vertices)
    assert _vertex_gap(cpu, gpu) < DEVICE_TOLERANCE * (2.0 / 2 ** cfg.max_depth)
