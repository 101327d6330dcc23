"""The sections of a reconstruction's :class:`Config`, one dataclass per stage, with the paper's or
the official code's values as defaults (``docs/ALGORITHMS.md``), and the rules derived from them
(the ``gpu`` training budget, the network widths of a depth). Thresholds of the field and of the
extractor are in *unit space* (the normalised frame of §0.1); quantities in millimetres say ``_mm``
in their name."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Mapping

from ..errors import InputError
from .introspection import check_choices, choices


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
    surface_fit_points: int = 0
    """Sparse clouds: where the median voxelised point has fewer than this many points (itself
    included) within ``surface_fit_mm``, the planes' radius grows by the square root of the
    shortfall (a surface's count grows with the square of the radius), at most to twice
    ``surface_fit_mm``, and every length taken from it with it (the false-echo columns and groups,
    the gaps bridged): the columns compare counts of echoes and the planes' spreads come from their
    neighbours, which a sparse neighbourhood holds too few of to tell bone from its band. The radius
    used is ``counts.plane_radius_mm``; 0 = ``surface_fit_mm`` as given."""
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
    where the points' probe positions are known, else the side the beams come from where the
    cloud's order tells them (``beams_from_order``), else the side away from which the bone bends
    (bone is mostly convex); echoes behind a layer are kept (both faces of a thin plate of bone are
    bone). Needs ``surface_fit_mm``; 0 = keep them."""
    beams_from_order: bool = False
    """``front_echo_mm`` on a cloud without probe positions: take the probe's side from the beams the
    cloud's own order tells, where it was written frame by frame, each frame's points row by row
    from the probe down (:mod:`~ultraboneudf.geometry.frame_order`); the side from the bone's bend
    where it tells none. False = always from the bend."""
    front_echo_ratio: float = 2.0
    """``front_echo_mm``: how many times denser the bone's layer must be than an echo's own layer (±1 mm
    along the column) for the echo to count as lying in front of it."""
    min_component: float = 0.0
    """After ``front_echo_mm``: drop the groups of points (linked across gaps under
    ``surface_fit_mm``) smaller than this fraction of the largest group — clusters of echoes
    detached from the bone — but not those holding a steep face's echoes (``steep_planes_deg``,
    sweeps: a small bone's steep sides return a few echoes apart from the rest), nor those lying in
    the plane of the kept surface where it is nearest to them (bone seen apart from the rest, past
    a gap in the coverage; a floating cluster lies off that plane); 0 = keep all."""
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
    (:mod:`~ultraboneudf.geometry.data_surface`; needs ``data.surface_fit_mm``). Between the slices of a
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
    """CPU threads of the training loop, at most PyTorch's setting (the cores, ``OMP_NUM_THREADS``);
    0 = PyTorch's setting. Small products run faster on few threads: the ``fast`` preset's step
    on one, the default's on two (docs/development.md). The count used is the sidecar's
    ``method_info.train_threads``; float sums, and so a run's last digits, follow it."""
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
    data_margin: float = 0.0
    """μ at least this × how far above zero the field stays on its own data: the 90th percentile
    of ``u`` at the pre-processed points; 0 = ``margin`` as given. A field trained on a thick,
    sparse band of echoes keeps its minimum above zero between the points, and a fixed μ leaves the
    surface there out; where the field reaches zero on its points ``margin`` stays. The margin used
    is ``counts.extract_margin`` in the sidecar."""
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
    trim_normal_sigmas: float = 0.0
    """The normal trim follows the data's band: where this × the median spread of the points
    about their local planes (a robust σ, mm) is under ``trim_normal_mm``, that is the distance
    used, but never under 0.4 mm; 0 = ``trim_normal_mm`` as given. A thin band (a bone boundary
    traced one echo per scan line) keeps the field's zero set within a few tenths of a millimetre
    of the data, and a sheet nearer than ``trim_normal_mm`` to it is still off the bone; on clean
    points the field and its extraction stay within 0.4 mm of the data's surface. The distance used
    is ``counts.trim_normal_mm`` in the sidecar."""
    trim_rim_mm: float = 0.0
    """A third support trim, past the data's rims where a sweep's probe looked: drop the faces whose
    mean vertex distance past the rim of the local planes' surface, within the image plane of the
    nearest point's frame, is ≥ this many mm; 0 = off. The field continues a sheet in its own plane
    past a rim, and the distance rule of ``trim_mm`` keeps that continuation for its whole length;
    within an image plane the probe looked on past the last echo and found no bone (a small bone's
    sides curving away from the beam), across the image planes it did not look. Needs the frames
    (``reconstruct SWEEP``, or ``frame_index=``): a cloud without them is not affected."""
    trim_grazing_deg: float = 0.0
    """A fourth trim, by the beams: drop the faces that the beams of the pre-processed points within
    3 mm of them (their mean) meet this many degrees or more from their normal; 0 = off. A bone face
    met nearly side-on sends no echo back to the probe: a face lying along the beams continues a
    streak of echoes along them (a segmentation's band running on past a steep side of the bone),
    not a surface they imaged. Needs the beams: a sweep's probe positions, or a cloud's order
    (``data.beams_from_order``); a cloud with neither is not affected."""
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
    solver slows down more than tenfold with 2 threads; use 1 there."""


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
        from .overrides import set_value

        cfg = cls()
        for section, values in data.items():
            for key, value in values.items():
                set_value(cfg, f"{section}.{key}", value)
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


GS_FORMS: tuple[str, ...] = choices(LossConfig, "gs_form")
"""The forms of ``L_GS`` (:attr:`LossConfig.gs_form`)."""
