"""Typed configuration of a reconstruction, the named presets, and overrides.

A :class:`Config` has one dataclass per stage. Every field carries the paper's or the official
code's value (see ``docs/ALGORITHMS.md``); the presets differ only where the two disagree (§1.11) and in
the ``fast`` preset designed here. Thresholds of the field and of the extractor are in *unit space*
(the normalised frame of §0.1); quantities in millimetres say ``_mm`` in their name.

Overrides are ``"section.field=value"`` strings (the CLI's ``--set``) or keyword arguments
(``iters=1000``, ``train__iters=1000``); a bare field name must be unique across sections.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field, fields
from functools import cache
from typing import Any, ClassVar, Literal, Mapping

from .errors import InputError


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


@cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a config section (the string literal that follows its
    annotation in the class body), ``""`` where there is none. Read from the source, which is the
    one place the fields are documented."""
    import ast
    import inspect
    import textwrap

    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    docs: dict[str, str] = {}
    for node, after in zip(body, body[1:] + [None]):
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            doc = ""
            if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) \
                    and isinstance(after.value.value, str):
                doc = " ".join(after.value.value.split())
            docs[node.target.id] = doc
    return {f.name: docs.get(f.name, "") for f in fields(cls)}


def choices(section: Any, name: str) -> tuple[str, ...] | None:
    """The allowed values of a mode field (annotated ``Literal[...]``) of a config section (a class
    or an instance), or ``None`` when the field is not a mode."""
    cls = section if isinstance(section, type) else type(section)
    hint = _hints(cls).get(name)
    return typing.get_args(hint) if typing.get_origin(hint) is Literal else None


def check_choices(section: Any) -> None:
    """Raise :class:`InputError` naming the ``--set`` key and the allowed values for every mode field
    of ``section`` that holds a value outside its ``Literal`` type."""
    for f in fields(section):
        _check_choice(section, f.name, getattr(section, f.name))


def _check_choice(section: Any, name: str, value: Any) -> None:
    allowed = choices(section, name)
    if allowed is not None and value not in allowed:
        raise InputError(f"unknown {section.SECTION}.{name} {value!r}; choose one of {', '.join(allowed)}")


class _Section:
    """Base of the config sections: the modes are checked on construction (and by :func:`validate`
    before a run, for values assigned later)."""

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        check_choices(self)


@dataclass
class DataConfig(_Section):
    """Pre-processing: down-sampling, surface subset, queries and anchors (§1.2–1.4)."""

    SECTION: ClassVar[str] = "data"

    voxel_size_mm: float = 0.1
    """Edge of the down-sampling voxel in mm (voxel mean, §1.2 step 2); 0 disables it."""
    max_voxels: int = 0
    """At most this many points after the voxel mean: a larger result is voxelised again with a
    coarser voxel (the edge used is ``counts.voxel_size_mm``), so the local-plane stage's cost is
    bounded on clouds of millions of points; 0 = no limit (the reference)."""
    subset: Literal["official", "fps", "all"] = "official"
    """Surface subset rule: ``official`` (FPS 5k ∪ FPS 15k when above ``subset_threshold`` points,
    else all), ``fps`` (FPS to ``max_points`` distinct points, all if fewer), ``all``."""
    subset_threshold: int = 60_000
    """Official rule: clouds with more points than this are reduced by FPS."""
    fps_sizes: tuple[int, ...] = (5_000, 15_000)
    """Official rule: the FPS sizes whose results are concatenated (duplicates kept)."""
    max_points: int = 40_000
    """``fps`` rule: number of distinct surface points."""
    sigma_k: int = 50
    """σ(p) = distance to the k-th nearest *other* point (§0.7)."""
    queries_per_point: int = 20
    """Gaussian queries per surface row (§1.3)."""
    grid_queries: int = 30_000
    """Far-field queries drawn from the two lattices of §0.8; 0 disables them."""
    drop_to_multiple: int = 1_000
    """Official: drop the last ``T mod drop_to_multiple`` stored queries (§1.3 step 4); 0 keeps all."""
    anchors: Literal["official", "bbox", "none"] = "official"
    """Global-shape anchors: ``official`` (10³ lattice on [−1, 1]³) or ``bbox`` (lattice over the
    bounding box of P, the paper's wording); ``none`` disables L_GS."""
    anchor_resolution: int = 10
    """Anchors per axis of the lattice."""
    anchor_squared_target: bool = True
    """Official: regress u(ρ) on the *squared* distance to P (§1.4, [!])."""
    anchor_min_target: float = 0.1
    """Keep anchors whose target exceeds this (official: squared distance > 0.1); a negative value
    keeps all."""
    surface_fit_mm: float = 0.0
    """Radius (mm) of the robust local plane fitted around every voxelised point
    (:mod:`~ultraboneudf.geometry.surface_fit`); 0 = none. ``denoise``, ``outlier_sigmas`` and the
    ``surface`` distance target (``loss.distance_target``) and ``bridge`` use these planes."""
    denoise: int = 0
    """Passes of: fit the local planes, drop the outliers (``outlier_sigmas``), move every point
    onto its plane. Removes the noise across the surface (ultrasound: along the beam) and the
    offsets between slices, keeps the points' spacing along it; a second pass fits thinner data.
    0 = the points stay where they are (the planes are fitted once if ``surface_fit_mm`` > 0)."""
    outlier_sigmas: float = 0.0
    """Drop the points farther from their local plane than this many times the plane's robust spread
    (and than a tenth of ``surface_fit_mm``), e.g. false echoes in the acoustic shadow, and isolated
    points; 0 = keep all."""
    steep_planes_deg: float = 0.0
    """Sweeps (points with probe positions): a point whose local plane faces the probe more steeply
    than 60° (which the planes refuse: false echoes streaking under the bone make such planes) but
    within this angle keeps that plane's orientation for the ``surface`` distance target and the
    support trim: the surface continues past it as past any rim (``rim_reach``), where a steep
    face's echo faded. It is not moved onto that plane nor judged by it, and it is kept where it is
    too sparse for a plane at ``surface_fit_mm`` but a wider radius gives it a steep one (a steep
    face returns few echoes), unless another point lies 3–10 mm above it on its beam (false echoes
    in the bone's shadow line up into steep planes too). 0 = such points have no plane and the
    surface ends at them."""
    shadow_mm: float = 0.0
    """Sweeps (points with probe positions): drop the points that lie this many mm or more (up to
    10 mm) beneath another point along their own beam, within half a millimetre of it — false echoes
    in the acoustic shadow of the bone (after ``denoise``); 0 = keep them."""
    front_echo_mm: float = 0.0
    """Drop the echoes up to this many mm in front of a denser layer of echoes (the bone's band) along
    its normal, on the probe's side (:mod:`~ultraboneudf.geometry.echo_layers`): soft-tissue sheets,
    clusters and streaks that real segmentations take for bone. The probe's side is the probe's
    where the points' probe positions are known, else the side away from which the bone bends
    (bone is mostly convex); echoes behind a layer are kept (both faces of a thin plate of bone are
    bone). Needs ``surface_fit_mm``; 0 = keep them."""
    front_echo_ratio: float = 2.0
    """``front_echo_mm``: how many times denser the bone's layer must be than an echo's own layer (±1 mm
    along the column) for the echo to count as lying in front of it."""
    min_component: float = 0.0
    """After ``front_echo_mm``: drop the groups of points (linked across gaps under
    ``surface_fit_mm``) smaller than this fraction of the largest group — clusters of echoes
    detached from the bone — but not those holding a steep face's echoes (``steep_planes_deg``,
    sweeps: a small bone's steep sides return a few echoes apart from the rest); 0 = keep all."""
    bridge: float = 0.0
    """Gaps in the data up to this × the local plane radius (``surface_fit_mm``, or the wider radius
    the fit needed, at most twice ``surface_fit_mm``) count as surface: for the ``surface`` distance target and for the support trim
    (``extract.trim_mm``, then measured to that surface instead of to the nearest point); 0 = none."""
    frame_bridge: float = 0.0
    """Sweeps whose frames are known (``reconstruct SWEEP``, or ``frame_index=``): a gap between two
    consecutive frames, across their image planes (a run of lost frames), counts as surface up to
    this × ``surface_fit_mm``; gaps inside a frame, or past a frame in between, where the probe
    looked and found no echo, keep ``bridge``. For the ``surface`` distance target and the support
    trim alike; and the target's ``rim_reach`` stops at the sweep's first and last image planes, past
    which the probe never looked. 0 = as ``bridge``, and no end planes."""
    rim_reach: float = 0.0
    """``surface`` distance target: past the last points (the rim of the data) the surface goes on
    for this × the local plane radius in each point's plane. Where an echo fades (oblique bone) the
    bone goes on past the last detection; 0 = the surface ends at the points."""
    noise_sigma_mm: float = 0.0
    """Gaussian noise (mm) added to the input before pre-processing (experiment E6); 0 = none."""
    queries: Literal["ultraboneudf", "capudf"] = "ultraboneudf"
    """Query recipe: ``ultraboneudf`` (§1.3, ``queries_per_point`` per row + grid queries) or
    ``capudf`` (§3.1: random subset of a multiple of 60 rows, spread κ·σ(p), ⌊total/N⌋ rounds)."""


@dataclass
class ModelConfig(_Section):
    """The MLP field (§0.3, §1.5)."""

    SECTION: ClassVar[str] = "model"

    hidden: tuple[int, ...] = (64, 128, 128, 256, 256, 256)
    """Hidden widths; the official network has 6 hidden layers (191,042 parameters)."""
    weight_norm: bool = True
    """Weight normalisation ``W = g·V/‖V‖`` on every layer (§0.3)."""
    geometric_init_radius: float = 0.5
    """β of the geometric initialisation: the initial field is |‖x‖ − β|."""
    abs_output: bool = True
    """Absolute value at the output (an unsigned distance field)."""
    skip: tuple[int, ...] = ()
    """Layers whose input is ``[h, x]/√2`` (§0.3; CAP-UDF and FUNSR: ``(4,)``). Empty: no skip (the
    UltraBoneUDF network, whose configured skip is inactive, §1.5)."""
    depth: int = 0
    """§6.4 depth rule: when > 0, ``hidden`` is replaced by the first ``depth`` entries of
    :data:`DEPTH_WIDTHS` (experiment E4); 0 uses ``hidden`` as given."""


@dataclass
class LossConfig(_Section):
    """Loss terms (§1.6)."""

    SECTION: ClassVar[str] = "loss"

    kind: Literal["tangent", "pull", "capudf"] = "tangent"
    """``tangent`` (UltraBoneUDF, dynamic nearest neighbour), ``pull`` (static target, §5.3) or
    ``capudf`` (CAP-UDF's consistency-aware L1 Chamfer between the batch targets and moved queries,
    §3.3). FUNSR has its own loop (§4.3) and ignores this."""
    pull_norm: Literal["squared", "unsquared"] = "squared"
    """``pull`` loss: ``squared`` (Eq. 3 as printed) or ``unsquared`` (FUNSR's code, §4.3)."""
    tangent_norm: Literal["l1", "l2"] = "l1"
    """Residual penalty of the tangent loss: ``l1`` (official code) or ``l2`` (paper, Eq. 6)."""
    lambda_tangent: float = 1.0
    """Weight of the tangent-plane loss (λ_NC, Eq. 8)."""
    lambda_gs: float = 0.01
    """Weight of the global-shape term L_GS on the anchors (λ_GS, Eq. 8)."""
    gs_form: Literal["per_anchor", "broadcast"] = "broadcast"
    """How ``L_GS`` pairs outputs and targets: ``per_anchor``, ``mean_i (u(ρ_i) − t_i)²`` (the paper's
    Eq. 7); ``broadcast``, ``mean_i mean_j (u(ρ_i) − t_j)²`` = ``mean_i (u(ρ_i) − mean t)² + var t``,
    what the reference computes (``nn.MSELoss`` of a (G, 1) output against (G,) targets broadcasts to
    G × G), which pulls every anchor toward the mean target instead of its own."""
    warm_start: float = 0.0
    """Fraction of ``train.iters`` at the start that regress ``u(q)`` on ``‖q − t(q)‖`` (L1, static
    nearest surface point) instead of the main loss; then the main loss takes over with the same
    optimiser and schedule. 0 = none (the reference). A short run starting from the initial sphere can leave a far part of
    the bone without a zero set; this puts one near every part of the cloud first."""
    lambda_far: float = 0.0
    """Weight of ``mean |u(q) − ‖q − t(q)‖|`` over the batch queries farther than ``far_threshold``
    from ``P`` (static nearest surface point), added to the main loss at every step after the warm
    start; 0 = off (the reference). It forbids zero sets away from the data, which a short run
    otherwise leaves behind an open surface."""
    far_threshold: float = 0.01
    """``lambda_far``: queries closer to ``P`` than this (unit space) are left to the main loss; 0 =
    the term acts on every query (the ``fast`` preset)."""
    distance_target: Literal["point", "surface"] = "point"
    """What ``warm_start`` and ``lambda_far`` regress ``u(q)`` on: ``point``, the distance to the
    nearest surface point ``t(q)`` (the reference's target); ``surface``, the distance to the surface
    interpolated between the points across gaps up to ``data.bridge``
    (:mod:`~ultraboneudf.geometry.support`; needs ``data.surface_fit_mm``). Between the slices of a
    sweep the nearest point lies beside the query, not under it: ``point`` then asks for a ridge of
    ``u`` between the slices."""
    gs_anchors: int = 0
    """Anchors drawn at random (with replacement) for ``L_GS`` at each step; 0 = all anchors every
    step (the reference). A subset is an unbiased estimate of the same loss at a fraction of the cost."""
    lambda_os: float = 0.0
    """On-surface term ``mean u(p)²`` over the surface points (Eq. 9): experiment E5, and the
    ``robust`` preset, where it holds the zero level on the data the tangent phase alone can leave
    above zero (a far part of the bone, seen by few frames)."""
    os_rows: int = 0
    """Surface points drawn at random (with replacement) for ``L_OS`` and ``L_Eik`` at each step;
    0 = all of them every step (the reference)."""
    lambda_eik: float = 0.0
    """Eikonal term (Eq. 10); experiment E5 only."""


@dataclass
class TrainConfig(_Section):
    """The per-scan optimisation (§1.7)."""

    SECTION: ClassVar[str] = "train"

    iters: int = 30_000
    """Optimiser steps (the command line's ``--iters``)."""
    batch: int = 5_000
    """Queries per step."""
    sampler: Literal["strided", "epoch"] = "strided"
    """Batch draw: ``strided`` (the reference, §0.5) or ``epoch`` (consecutive batches of one
    permutation of all stored queries per pass)."""
    threads: int = 0
    """CPU threads of the training loop; 0 = PyTorch's setting. A small batch runs faster on one
    thread (measured at batch 250 on 2 cores: 22 ms/step on one, 26 ms on two)."""
    step: Literal["optimised", "plain"] = "optimised"
    """``optimised`` (hand-written input gradient and fused Adam) or ``plain`` (autograd's double
    backward and PyTorch's default Adam): the same losses and updates (tested to fp32 precision)."""
    lr: float = 1e-3
    """Peak learning rate of Adam, reached after ``warmup`` steps, then a cosine decay to 0 (§0.6)."""
    warmup: int = 1_000
    """Linear warm-up iterations from lr = 0 (§0.6)."""
    budget: Literal["auto", "reference", "cpu", "gpu"] = "reference"
    """How many steps of how many queries. ``reference``: the baselines' published schedules (CAP-UDF
    60,000 steps, FUNSR 15,000) and 256³ grids; ``cpu``: this section's ``iters`` and ``batch``
    (CAP-UDF expands after two thirds of them) and 128³ grids; ``gpu``: as ``cpu``, but UltraBoneUDF
    takes a quarter of the steps and of the warm-up with 16 times the queries at twice the learning
    rate (a GPU's step costs about the same at either batch); ``auto``: ``gpu`` on a CUDA device,
    else ``cpu``. The sidecar's ``method_info`` holds the schedule UltraBoneUDF used."""
    cuda_graph: bool = True
    """On a CUDA device, capture the training step in a CUDA graph after a few eager steps and
    replay it (the same step without the per-operation launch cost); false, or where capture is not
    possible, runs every step eagerly (the progress log says why). The CPU always steps eagerly."""


@dataclass
class ExtractConfig(_Section):
    """The extractor (``mode``) and, after it, the support trim and the data-fit self-check; the
    DualMesh-UDF octree and vertex thresholds (§2, unit space), which the ``faithful`` and ``clean``
    extractors share. Defaults: the UltraBoneUDF call of §1.8. The edge-crossing extractor's own
    options are :class:`CleanConfig`, the grid extractors' :class:`GridConfig`."""

    SECTION: ClassVar[str] = "extract"

    max_depth: int = 9
    """Octree depth D over ``domain`` (leaves of edge ``(hi − lo) / 2^D``); the reference's 9 over
    [−1, 1]³ is 256 cells across the object's longest side (§2.2)."""
    sampling_depth: int = 1
    """Sub-lattice per leaf: ``(2^s + 1)³`` samples of the UDF and its gradient (§2.4)."""
    margin: float = 0.002
    """Subdivision margin μ (unit space): a cell is kept while ``u(centre) < half diagonal + μ`` (§2.3)."""
    valid_threshold: float = 0.01
    """Projection-validity threshold τ_val (unit space): a sample counts only if the UDF at its
    projection ``x − u·ĝ`` is below this (§2.5)."""
    min_udf: float = 1e-6
    """τ_min (unit space): samples with ``u`` at or below this are left out of the vertex solve, their
    gradient being undefined on the zero set (§2.6)."""
    corner_factor: float = 1.0
    """A corner vertex is accepted inside its leaf enlarged by this fraction of the leaf edge on every
    side (f_c, §2.6)."""
    edge_factor: float = 1.0
    """An edge (line) vertex takes the line's crossings of the leaf's faces, or failing those, of the
    leaf enlarged by this fraction of its edge (f_e, §2.6)."""
    plane_factor: float = 1.0
    """A plane vertex takes the plane's crossings of the leaf's edges, or failing those, of the leaf
    enlarged by this fraction of its edge (f_p, §2.6)."""
    sv_threshold: float = 0.2
    """Relative singular-value cut τ_sv of the vertex solve: singular values below this × the largest
    count as zero (the vertex type: 3 left = corner, 2 = edge, 1 = plane; §2.6)."""
    dedup_eps: float = 1e-15
    """ε_dup (unit space): vertices closer than this are merged after meshing (§2.10)."""
    batch: int = 150_000
    """Points per field evaluation."""
    band_start_depth: int = 0
    """§2.3 subdivision: octree levels shallower than this keep every cell without testing its centre
    (0 = the reference). The test assumes u never exceeds the distance to the surface; a field that
    overestimates far away (e.g. u = 1.11 at (±0.5, ±0.5, ±0.5) for the ``paper`` femur field, true
    distance ≈ 0.5) otherwise drops whole octants that contain surface."""
    domain: tuple[float, float] = (-1.0, 1.0)
    """The octree cube [lo, hi]³ in unit space."""
    mode: Literal["faithful", "clean", "capudf_mc", "sdf_mc", "udf2sdf"] = "faithful"
    """``faithful`` reproduces DualMesh-UDF; ``clean`` returns a one-layer manifold-edged mesh;
    the grid extractors (``extraction/marching.py``): ``capudf_mc`` (CAP-UDF pseudo-sign per-cell
    marching cubes, §3.5), ``sdf_mc`` (marching cubes of a signed field, §4.5), ``udf2sdf``
    (CarotidUDF, §5.4)."""
    trim_mm: float = 0.0
    """Support trim, after any extractor and for every method: drop the faces whose mean vertex
    distance to the nearest pre-processed input point (the voxelised cloud) is ≥ this many mm;
    0 = off (the reference). It removes zero sets the field keeps away from the data (a sheet
    continued past the rim of an open surface, remnants of the initial sphere); a gap in the data
    wider than about twice this value opens as a hole."""
    trim_normal_mm: float = 0.0
    """A second support trim, along the data's surface normal: drop the faces whose mean vertex
    distance from the surface of the local planes (``data.surface_fit_mm``), measured along its
    normal, is ≥ this many mm; 0 = off. A noisy band of points leaves shallow minima in the field
    that the extractor meshes as sheets a millimetre or two under or over the bone, which the
    distance rule of ``trim_mm`` keeps; a surface continued in its own plane past a rim is not
    affected."""
    min_leaf_mm: float = 0.0
    """Leaves no smaller than this (mm): the octree depth is lowered from ``max_depth`` until the leaf
    edge reaches it, so a small bone is not meshed at a resolution finer than the data resolve (a
    noisy field's minimum then stays above the band and crossing thresholds, which scale with the
    leaf); 0 = ``max_depth`` as given. The depth used is ``counts.extract_depth`` in the sidecar."""
    fit_mm: float = 3.0
    """Data-fit self-check (sidecar ``data_fit``, a warning from the CLI): the fraction of input
    points farther than this many mm from the mesh, and of mesh area this far from every input point;
    0 = off. It measures, never changes, the mesh."""


@dataclass
class CleanConfig(_Section):
    """The edge-crossing extractor (``extract.mode=clean``): one layer of surface, every edge shared by
    at most two faces, on the DualMesh-UDF octree band (``extract.*``)."""

    SECTION: ClassVar[str] = "clean"

    crossing: float = 0.5
    """A leaf-lattice edge whose end gradients oppose counts as crossed only if the UDF
    at the estimated crossing is below ``crossing × leaf edge + extract.margin``."""
    vertex: Literal["qef", "mass"] = "qef"
    """The vertex: ``qef`` (the §2.6 vertex of the leaf if within ``qef_window`` cells
    of it, else the mean of the leaf's crossing points) or ``mass`` (always that mean)."""
    qef_window: float = 0.5
    """How far (in leaf cells) outside its leaf a QEF vertex may lie and still be used."""
    project_steps: int = 2
    """Projection steps x ← x − α·u·∇u/|∇u| moving vertices onto the zero set; 0 = none."""
    merge: float = 1e-6
    """Vertices that round to the same point of a grid of this many leaf cells merge."""
    unfold_deg: float = 0.0
    """Fold repair: a vertex off the mesh's rim on an edge whose two faces meet at more than this
    many degrees moves to the mean of its neighbours and takes one projection step onto the zero
    set; 0 = off. A field whose minimum is a band (trained on noisy points) scatters the QEF vertices
    across it, and the zigzag adds area without accuracy."""
    unfold_passes: int = 3
    """At most this many rounds of the fold repair (``unfold_deg``)."""


@dataclass
class GridConfig(_Section):
    """The grid extractors of the baselines (``extract.mode`` ``capudf_mc``, ``sdf_mc``, ``udf2sdf``;
    ``extraction/marching.py``); lengths in unit space."""

    SECTION: ClassVar[str] = "grid"

    resolution: int = 256
    """Grid points per axis."""
    box: Literal["domain", "surface"] = "domain"
    """``domain`` (the cube ``extract.domain``³, FUNSR/CarotidUDF) or ``surface`` (bounding box of the
    surface points enlarged by ``box_margin`` per side, CAP-UDF)."""
    box_margin: float = 0.05
    """``box = surface``: enlargement per side (unit space)."""
    cell_threshold: float = 0.005
    """``capudf_mc`` / ``local-flip``: skip cells whose smallest corner value exceeds this."""
    udf2sdf: Literal["normal-sign", "eps-shell", "local-flip"] = "normal-sign"
    """``extract.mode=udf2sdf`` conversion: ``normal-sign`` (default), ``eps-shell`` or
    ``local-flip`` (§5.4)."""
    udf2sdf_project: bool = False
    """``eps-shell``: project the vertices onto the zero set with ``v ← v − u·ĝ``."""
    far: float = -1.0
    """``capudf_mc``: drop faces whose mean vertex distance to the surface points is ≥ this; ≤ 0 = off."""


@dataclass
class PoissonConfig(_Section):
    """The screened-Poisson baseline (``--method poisson``, §7)."""

    SECTION: ClassVar[str] = "poisson"

    octree_depth: int = 9
    """Octree depth of the screened Poisson solver (§7)."""
    scale: float = 1.1
    """The octree cube is this × the input's bounding cube."""
    normals: Literal["ultraboneudf", "knn30"] = "ultraboneudf"
    """Normals (§7.2): ``ultraboneudf`` (PCA radius 0.5, ≤ 1,000 neighbours) or
    ``knn30`` (PCA over 30 neighbours); oriented as ``orientation`` says."""
    orientation: Literal["auto", "tangent", "probe"] = "auto"
    """Normal orientation (§7.2): ``tangent`` (tangent-plane propagation, 15
    neighbours), ``probe`` (each normal turned toward the probe position of its point, alternative B;
    needs per-point probe positions: a sweep input or ``reconstruct(..., probe_positions=…)``) or
    ``auto`` (``probe`` when probe positions are present, else ``tangent``)."""
    backend: Literal["auto", "pymeshlab", "open3d"] = "auto"
    """The Poisson library: ``auto`` (first installed of pymeshlab, open3d), ``pymeshlab`` or ``open3d``."""
    solver_threads: int = 0
    """Solver threads; 0 = ``torch.get_num_threads()``. On an oversubscribed CPU the OpenMP
    solver slows down > 10× with 2 threads (measured 2 s → 34 s); use 1 there."""


@dataclass
class CapudfConfig(_Section):
    """CAP-UDF (``--method capudf``, §3): its query recipe's size and the progressive expansion."""

    SECTION: ClassVar[str] = "capudf"

    total_queries: int = 1_000_000
    """``data.queries=capudf``: about this many queries in all (rounds = ⌊total / N⌋)."""
    expand_at: int = 0
    """Progressive expansion (§3.4): after this many iterations densify ``P`` and switch to
    ``expand_batch``; 0 = never (one stage)."""
    expand_batch: int = 20_000
    """Stage-2 batch size."""
    expand_candidates: int = 1_000_000
    """Generated candidate surface points (``eval_num_points``)."""
    expand_df_filter: float = 0.01
    """Keep candidates whose predicted distance is below this (unit space)."""
    expand_low_range: float = 1.1
    """Candidate spread = this × the std of the batch offsets ``q − t``."""
    expand_outlier: float = 0.002
    """Discard candidates at distance ≥ this from ``P`` (unit space)."""
    expand_rate: float = 1.0
    """Keep about ``expand_rate · N`` candidates (``extra_points_rate``), spread evenly."""


@dataclass
class FunsrConfig(_Section):
    """FUNSR (``--method funsr``, §4): the sign-consistency and adversarial terms."""

    SECTION: ClassVar[str] = "funsr"

    lambda_scc: float = 0.005
    """Sign-consistency weight (§4.3)."""
    lambda_adl: float = 0.005
    """Adversarial on-surface weight (§4.3)."""
    disc_lr: float = 1e-3
    """Discriminator learning rate (constant, §4.4)."""


@dataclass
class Config:
    """A whole reconstruction's configuration."""

    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    extract: ExtractConfig = field(default_factory=ExtractConfig)
    clean: CleanConfig = field(default_factory=CleanConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    poisson: PoissonConfig = field(default_factory=PoissonConfig)
    capudf: CapudfConfig = field(default_factory=CapudfConfig)
    funsr: FunsrConfig = field(default_factory=FunsrConfig)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (tuples become lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Config":
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InputError`."""
        cfg = cls()
        for section, values in data.items():
            for key, value in values.items():
                _set(cfg, f"{section}.{key}", value)
        return cfg


# The DualMesh-UDF official driver values (§2.11): the generic defaults of the extractor.
DMU_DEFAULTS: dict[str, Any] = dict(
    max_depth=7, valid_threshold=0.002, min_udf=0.002, corner_factor=1.0, edge_factor=1.0,
    plane_factor=0.15, sv_threshold=0.08, dedup_eps=1e-7,
)


def _official() -> Config:
    return Config()


def _paper() -> Config:
    cfg = Config()
    cfg.data = DataConfig(subset="fps", max_points=40_000, grid_queries=0, drop_to_multiple=0,
                          anchors="bbox", anchor_squared_target=False, anchor_min_target=-1.0)
    cfg.loss.tangent_norm = "l2"
    cfg.loss.gs_form = "per_anchor"
    # 256 cells across the object (depth 9 on [−1, 1]³) with the official DMU thresholds (§1.11).
    cfg.extract = ExtractConfig(**{**DMU_DEFAULTS, "max_depth": 9})
    # Without grid queries the far field is free to overestimate; test the band from 0.125-unit cells.
    cfg.extract.band_start_depth = 4
    cfg.extract.mode = "clean"  # one-layer, edge-manifold mesh; "faithful" reproduces DMU
    cfg.extract.trim_mm = 3.0   # no surface > 3 mm from the data (README, "Support trim")
    cfg.clean.project_steps = 0  # see _fast
    return cfg


def _fast() -> Config:
    """Designed for a 100k-point cloud on a 2-core CPU (measured in docs/results.md).

    What limits a short run is the number of optimiser steps: the tangent loss grows the zero set
    outward from the initial sphere and can leave a part of the bone without one. A warm start
    (regressing u on the distance to P) first puts a zero set near every part of the data; the
    far-field term, applied to every query, keeps forbidding zero sets away from the data and pins u
    to the distance near it, so the zero set reaches the open rims. A 64-wide network is as accurate
    as 128 here at half the work; the epoch sampler and 128 random anchors a step for L_GS cut the
    per-step overhead.
    """
    cfg = Config()
    cfg.data.subset = "fps"
    cfg.data.max_points = 10_000
    cfg.data.queries_per_point = 20
    cfg.data.grid_queries = 10_000
    cfg.data.drop_to_multiple = 0
    cfg.model.hidden = (64, 64, 64, 64)
    cfg.model.geometric_init_radius = 0.1
    cfg.loss.gs_form = "per_anchor"
    cfg.loss.warm_start = 0.1
    cfg.loss.lambda_far = 1.0
    cfg.loss.far_threshold = 0.0
    cfg.loss.gs_anchors = 128
    cfg.train.iters = 10_000
    cfg.train.batch = 250
    cfg.train.sampler = "epoch"
    cfg.train.threads = 1
    cfg.train.warmup = 400
    cfg.train.lr = 2e-3
    cfg.train.budget = "auto"
    cfg.extract.max_depth = 8
    cfg.extract.mode = "clean"
    cfg.extract.trim_mm = 3.0
    # Trained fields' minima are not their exact zero sets: moving the QEF vertices onto them cost
    # accuracy on every field measured (docs/results.md, "Presets").
    cfg.clean.project_steps = 0
    return cfg


def _robust() -> Config:
    """``fast`` made for what ultrasound gives: noisy, slice-structured, gappy points with false echoes.

    A robust plane is fitted to the points within 4 mm of every point (mm, before normalisation):
    points more than three robust spreads from it are dropped (false echoes in the shadow, isolated
    detections) and the rest are moved onto it (noise along the beam, offsets between slices). The
    warm start and the far-field term regress ``u`` on the distance to the surface interpolated
    between the points across gaps up to the plane's radius (across a sweep's frames, when they are
    known, up to 10 mm: a run of lost frames), instead of the distance to the nearest point, which
    between slices lies beside the query rather than under it; past the data's rims that surface
    goes on for half the plane radius (2 mm), where an oblique echo faded (not past a sweep's first
    and last image planes, past which the probe never looked), also past the few echoes of a steep
    face (planes 60–80° from the beam orient the surface there without moving the points, and keep
    them where they are too sparse for a plane at 4 mm). The support trim measures to the bridged
    surface, so bridged gaps stay closed, and also drops the faces 1 mm or more from it along its
    normal (sheets the noise band leaves under or over the bone). ``L_OS`` on 256 surface points a
    step pins the zero level to the data where few frames saw the bone and the tangent phase alone
    leaves the field above zero there. Leaves are kept ≥ 0.75 mm, so a small bone is not meshed
    finer than its data resolve, and the mesh's folds (faces meeting at more than 60°, where the QEF
    vertices scatter across the noisy field's minimum) are smoothed out. The network is twice as
    wide as ``fast``'s (4 × 128): on these points it follows the denoised surface more closely, for
    1.6–1.8× the time (docs/robustness.md measures each part)."""
    cfg = _fast()
    cfg.model.hidden = (128, 128, 128, 128)
    cfg.data.max_voxels = 200_000
    cfg.data.surface_fit_mm = 4.0
    cfg.data.denoise = 1
    cfg.data.outlier_sigmas = 3.0
    cfg.data.bridge = 1.0
    cfg.data.frame_bridge = 2.5
    cfg.data.rim_reach = 0.5
    cfg.data.steep_planes_deg = 80.0
    cfg.data.front_echo_mm = 30.0
    cfg.data.min_component = 0.02
    cfg.loss.distance_target = "surface"
    cfg.loss.lambda_os = 10.0
    cfg.loss.os_rows = 256
    cfg.extract.min_leaf_mm = 0.75
    cfg.extract.trim_normal_mm = 1.0
    cfg.clean.unfold_deg = 60.0
    return cfg


GPU_STEP_DIVISOR = 4
"""``train.budget = gpu``: UltraBoneUDF runs this many times fewer steps (and a warm-up this much
shorter), with this many times the ``L_GS`` anchors and ``L_OS`` rows a step."""
GPU_BATCH_FACTOR = 16
"""``train.budget = gpu``: UltraBoneUDF's queries per step, this many times ``train.batch``."""
GPU_LR_FACTOR = 2.0
"""``train.budget = gpu``: UltraBoneUDF's peak learning rate, this many times ``train.lr``. With a
quarter of the steps the zero set must grow as far in larger steps, which the 16 times larger
batch (a quarter of the gradient noise) keeps stable; on the hard femur sweep of the robustness
benchmark (a CPU run, seed 0) the default's CD was 0.272 mm, the ``gpu`` budget's 0.316 mm at the
same rate and 0.279 mm at twice it."""


def resolve_budget(budget: str, device_type: str) -> str:
    """``train.budget`` as a run on a ``device_type`` (``cpu``, ``cuda``) device takes it: ``auto`` is
    ``gpu`` on CUDA, else ``cpu``; the other values as they are."""
    if budget == "auto":
        return "gpu" if device_type == "cuda" else "cpu"
    return budget


def training_schedule(loss: LossConfig, train: TrainConfig, device_type: str) -> tuple[LossConfig, TrainConfig]:
    """The ``loss`` and ``train`` sections UltraBoneUDF trains with on a ``device_type`` device:
    under the ``gpu`` budget (``auto`` on CUDA) copies with :data:`GPU_STEP_DIVISOR` times fewer
    steps and a warm-up as much shorter, :data:`GPU_BATCH_FACTOR` times the queries a step,
    :data:`GPU_STEP_DIVISOR` times the anchors and surface rows a step (the same number over the
    run) and :data:`GPU_LR_FACTOR` times the learning rate; otherwise the sections given. Their
    ``budget`` is the resolved one."""
    budget = resolve_budget(train.budget, device_type)
    if budget != "gpu":
        return loss, train if budget == train.budget else dataclasses.replace(train, budget=budget)
    f = GPU_STEP_DIVISOR
    train = dataclasses.replace(train, budget=budget, iters=max(1, round(train.iters / f)),
                                batch=train.batch * GPU_BATCH_FACTOR, warmup=round(train.warmup / f),
                                lr=train.lr * GPU_LR_FACTOR)
    loss = dataclasses.replace(loss, gs_anchors=loss.gs_anchors * f, os_rows=loss.os_rows * f)
    return loss, train


DEPTH_WIDTHS: tuple[int, ...] = (64, 128, 128, 256, 256, 256, 256, 256, 256, 256)
"""§6.4: hidden widths of a depth-``d`` network are the first ``d`` entries (depth 6 = default)."""


def model_widths(model: ModelConfig) -> tuple[int, ...]:
    """The hidden widths of ``model`` after the §6.4 depth rule."""
    if model.depth > len(DEPTH_WIDTHS):
        raise InputError(f"model.depth must be between 1 and {len(DEPTH_WIDTHS)}, got {model.depth}")
    widths = tuple(int(w) for w in model.hidden) if model.depth <= 0 else DEPTH_WIDTHS[: model.depth]
    bad = [int(k) for k in model.skip if not 1 <= int(k) <= len(widths)]
    if bad:
        raise InputError(f"model.skip={tuple(int(k) for k in model.skip)} needs layers 1..{len(widths)} "
                         f"({len(widths)} hidden layers); use a deeper network or --set model.skip=")
    return widths


PRESETS = {"robust": _robust, "fast": _fast, "official": _official, "paper": _paper}

DEFAULT_PRESET = "robust"
"""What ``reconstruct`` uses unless told otherwise: the best result on ultrasound-like data on a CPU."""

PRESET_HELP = {
    "robust": "the default: noisy, gappy, slice-structured ultrasound points with false echoes; "
              "about a minute for 50,000 points on a 2-core CPU",
    "fast": "robust without the noise handling: clean, dense clouds (e.g. sampled from a mesh)",
    "official": "the public reference code reproduced, deviations included (a GPU run: about an hour "
                "on a 2-core CPU)",
    "paper": "the paper's text where it differs from the code (a GPU run)",
}
"""One line per preset: which to use when (``--help`` and the README)."""

UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 0.001}
"""Millimetres per unit of the units a point cloud file may be given in (``reconstruct --units``)."""

def preset(name: str) -> Config:
    """A fresh :class:`Config` of the named preset (``robust``, ``fast``, ``official`` or ``paper``)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise InputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None


def _sections(cfg: Config) -> dict[str, Any]:
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)}


MOVED_KEYS = {
    **{f"model.poisson_{old}": f"poisson.{new}" for old, new in (
        ("depth", "octree_depth"), ("scale", "scale"), ("normals", "normals"), ("orientation", "orientation"),
        ("backend", "backend"), ("threads", "solver_threads"))},
    **{f"train.expand_{name}": f"capudf.expand_{name}" for name in (
        "at", "batch", "candidates", "df_filter", "low_range", "outlier", "rate")},
    "data.capudf_total_queries": "capudf.total_queries", "loss.lambda_scc": "funsr.lambda_scc",
    "loss.lambda_adl": "funsr.lambda_adl", "train.disc_lr": "funsr.disc_lr",
    **{f"extract.{name}": f"grid.{name}" for name in (
        "resolution", "box_margin", "cell_threshold", "udf2sdf", "udf2sdf_project", "far")},
    "extract.grid_box": "grid.box",
    **{f"extract.clean_{name}": f"clean.{name}" for name in (
        "crossing", "vertex", "qef_window", "project_steps", "merge")},
}
"""Keys of earlier versions that a method's or an extractor's own section now holds: old → new."""


def _resolve_key(cfg: Config, key: str) -> tuple[Any, str]:
    key = key.replace("__", ".")
    if key in MOVED_KEYS:
        raise InputError(f"config key {key!r} is now {MOVED_KEYS[key]!r}")
    sections = _sections(cfg)
    if "." in key:
        section, name = key.split(".", 1)
        if section not in sections:
            raise InputError(f"unknown config section {section!r} in {key!r}; "
                             f"sections: {', '.join(sections)}")
        obj = sections[section]
        if name not in {f.name for f in fields(obj)}:
            raise InputError(f"unknown config key {key!r}")
        return obj, name
    owners = [obj for obj in sections.values() if key in {f.name for f in fields(obj)}]
    if len(owners) != 1:
        what = "ambiguous" if owners else "unknown"
        raise InputError(f"{what} config key {key!r}; write it as section.{key}")
    return owners[0], key


def _optional(hint: Any) -> Any:
    """``X`` for a hint ``X | None`` (``Optional[X]``), else ``None``."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and len(args) == 2 and type(None) in args:
        return next(a for a in args if a is not type(None))
    return None


def _expected(hint: Any) -> str:
    """How a value of type ``hint`` is written on the command line (for error messages)."""
    if _optional(hint) is not None:
        return _expected(_optional(hint)) + " or none"
    if typing.get_origin(hint) is tuple:
        inner = typing.get_args(hint)[0]
        return "comma-separated " + ("integers" if inner is int else "numbers")
    return {bool: "true or false", int: "an integer", float: "a number"}.get(hint, "a string")


def coerce(hint: Any, value: Any, key: str) -> Any:
    """Convert ``value`` (possibly a string from the command line) to the type ``hint`` of a
    dataclass field (``bool``, ``int``, ``float``, ``str``, ``tuple[...]``, or one of them ``| None``,
    written ``none``); :class:`InputError` naming ``key`` and the expected type otherwise."""
    if _optional(hint) is not None:
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null")):
            return None
        return coerce(_optional(hint), value, key)
    try:
        if typing.get_origin(hint) is tuple:
            if isinstance(value, str):
                value = json.loads("[" + value.strip("()[] ") + "]")
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ValueError(value)
            inner = typing.get_args(hint)[0]
            return tuple(coerce(inner, v, key) for v in value)
        if hint is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                if low not in {"true", "false", "1", "0", "yes", "no"}:
                    raise ValueError(value)
                return low in {"true", "1", "yes"}
            if not isinstance(value, bool):
                raise ValueError(value)
            return value
        if hint in (int, float):
            if isinstance(value, str):
                value = json.loads(value)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(value)
            if hint is int:
                if float(value) != int(value):
                    raise ValueError(value)
                return int(value)
            return float(value)
        if not isinstance(value, str):
            raise ValueError(value)
        return value
    except (ValueError, TypeError, OverflowError, json.JSONDecodeError):
        raise InputError(f"bad value {value!r} for config key {key!r} (expected {_expected(hint)})") from None


def _set(cfg: Config, key: str, value: Any) -> None:
    obj, name = _resolve_key(cfg, key)
    hint = _hints(type(obj))[name]
    value = coerce(str if choices(obj, name) else hint, value, key)
    _check_choice(obj, name, value)
    setattr(obj, name, value)


MAX_DEPTH = 11
"""Deepest octree a run may ask for (2,048 leaves per axis; depth 12 exceeds a workstation's memory)."""


GS_FORMS: tuple[str, ...] = choices(LossConfig, "gs_form")
"""The forms of ``L_GS`` (:attr:`LossConfig.gs_form`)."""


def validate(cfg: Config, trains: bool = True) -> Config:
    """Raise :class:`InputError` for values no run can use (named by their ``--set`` spelling);
    returns ``cfg``. ``trains``: the method trains a network (Poisson does not, and sets no
    iterations)."""
    problems = []

    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            section, name = key.split(".")
            problems.append(f"{key}={getattr(getattr(cfg, section), name)!r} ({what})")

    for section in _sections(cfg).values():
        check_choices(section)
        for f in fields(section):
            value = getattr(section, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                problems.append(f"{section.SECTION}.{f.name}={value!r} (a finite number)")
    t, d, e, lo = cfg.train, cfg.data, cfg.extract, cfg.loss
    need(t.iters >= (1 if trains else 0), "train.iters", "at least 1")
    need(t.batch >= 1, "train.batch", "at least 1")
    need(math.isfinite(t.lr) and 0 < t.lr <= 1, "train.lr", "a learning rate in (0, 1]")
    need(t.warmup >= 0, "train.warmup", "0 or more")
    need(0.0 <= lo.warm_start < 1.0, "loss.warm_start", "a fraction in [0, 1)")
    need(1 <= e.max_depth <= MAX_DEPTH, "extract.max_depth", f"between 1 and {MAX_DEPTH}")
    need(cfg.grid.resolution >= 2, "grid.resolution", "at least 2")
    for key in ("data.voxel_size_mm", "data.surface_fit_mm", "data.bridge", "data.frame_bridge", "data.rim_reach",
                "data.shadow_mm", "data.outlier_sigmas", "extract.trim_mm", "extract.trim_normal_mm",
                "extract.fit_mm", "extract.min_leaf_mm"):
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        need(math.isfinite(value) and value >= 0, key, "finite and 0 or more")
    if e.trim_normal_mm > 0 and d.surface_fit_mm <= 0:
        problems.append("extract.trim_normal_mm needs the local planes: set data.surface_fit_mm > 0")
    need(d.denoise >= 0, "data.denoise", "0 or more passes")
    need(d.steep_planes_deg == 0 or 60 < d.steep_planes_deg < 90, "data.steep_planes_deg",
         "0 (none) or an angle between 60 and 90 degrees")
    need(d.max_voxels >= 0, "data.max_voxels", "0 (no limit) or more")
    need(lo.gs_anchors >= 0, "loss.gs_anchors", "0 (all) or more")
    need(lo.os_rows >= 0, "loss.os_rows", "0 (all) or more")
    if problems:
        raise InputError("bad configuration: " + "; ".join(problems))
    return cfg


def apply_overrides(cfg: Config, overrides: Mapping[str, Any] | None = None,
                    assignments: list[str] | tuple[str, ...] = ()) -> Config:
    """Apply keyword overrides and ``key=value`` strings to ``cfg`` in place; returns ``cfg``."""
    for key, value in (overrides or {}).items():
        _set(cfg, key, value)
    for item in assignments:
        if "=" not in item:
            raise InputError(f"--set expects key=value, got {item!r}")
        key, value = item.split("=", 1)
        _set(cfg, key.strip(), value.strip())
    return cfg
