"""End-to-end reconstruction on a small analytic open surface, on the CPU."""

import dataclasses
import hashlib

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

import ultraboneudf
from ultraboneudf.errors import InputError
from ultraboneudf.evaluation import evaluate

# A quarter-cylinder patch (radius 20 mm, 40 mm long): open, curved, known exactly.
RADIUS, LENGTH = 20.0, 40.0
SMALL = {"train.iters": 400, "train.batch": 1000, "train.warmup": 50, "extract.max_depth": 7,
         "data.max_points": 3000, "model.hidden": (64, 64, 64)}


def patch_points(n=4000, seed=0):
    rng = np.random.default_rng(seed)
    theta = rng.uniform(np.pi / 4, 3 * np.pi / 4, n)
    return np.c_[RADIUS * np.cos(theta), rng.uniform(0, LENGTH, n), RADIUS * np.sin(theta)]


def patch_mesh(n=200):
    theta = np.linspace(np.pi / 4, 3 * np.pi / 4, n)
    y = np.linspace(0, LENGTH, n)
    tt, yy = np.meshgrid(theta, y, indexing="ij")
    v = np.c_[RADIUS * np.cos(tt.ravel()), yy.ravel(), RADIUS * np.sin(tt.ravel())]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return trimesh.Trimesh(v, np.r_[np.c_[a, b, c], np.c_[a, c, d]], process=False)


@pytest.fixture(scope="module")
def small_run():
    return ultraboneudf.reconstruct(patch_points(), preset="fast", device="cpu", seed=3, **SMALL)


def test_end_to_end_chamfer_bound(small_run):
    """Bounds, for a 40 mm patch at depth 7 on [−1, 1]³ (leaf cell 40/64 = 0.625 mm) after only 400
    iterations (the presets train 2,000–30,000):

    - accuracy (mean reconstruction → truth) < 0.3 mm, under half a cell: where the mesh exists it
      lies on the surface; a broken loss, normalisation or unit error gives millimetres to tens of mm;
    - CD < 1.25 mm (2 cells, 3% of the object): a short run under-fits the field near the open edges,
      so the mesh stops up to a few mm short of them and completeness (truth → mesh) dominates CD.
    """
    rec = small_run
    assert rec.mesh is not None and len(rec.mesh.faces) > 100
    res = evaluate(rec.mesh, patch_mesh(), samples=200_000, seed=0)
    assert res.d_rg_mean_mm < 0.3, res
    assert res.cd_mm < 1.25, res
    # the mesh is in millimetres, in the input's frame
    lo, hi = rec.mesh.bounds
    assert np.all(lo > [-16, -2, 12]) and np.all(hi < [16, 42, 22])


def test_sidecar_contents(small_run, tmp_path):
    rec = small_run
    sidecar = rec.sidecar()
    for key in ("method", "preset", "config", "timings", "counts", "device", "seed", "version", "input",
                "mesh_quality", "data_fit"):
        assert key in sidecar
    # a Python run records its input too: the array's count and hash, so rec.save() has provenance
    arr = np.ascontiguousarray(patch_points(), dtype=np.float64)
    assert sidecar["input"] == {"source": "points", "points": len(arr),
                                "points_sha256": hashlib.sha256(arr.tobytes()).hexdigest()}
    # the 3 mm support trim leaves no face ≥ 3 mm (the self-check's distance) from the data
    fit = sidecar["data_fit"]
    assert fit["threshold_mm"] == rec.config.extract.fit_mm == 3.0
    assert fit["mesh_far_area_fraction"] == 0.0
    # the input's uncovered fraction (the short run stops short of the open edges) agrees with the
    # input's distances in mm to 10× denser mesh samples: the check sees mesh and data in one frame
    dense, _ = trimesh.sample.sample_surface(rec.mesh, 1_000_000, seed=5)
    exact, _ = cKDTree(dense).query(patch_points())
    assert fit["input_far_fraction"] == pytest.approx((exact > 3.0).mean(), abs=0.02)
    assert fit["input_p95_mm"] == pytest.approx(np.percentile(exact, 95), abs=0.3)
    # the fast preset extracts in clean mode: one layer, no edge shared by more than two faces
    quality = sidecar["mesh_quality"]
    assert quality["nonmanifold_edges"] == 0 and quality["duplicate_faces"] == 0
    assert quality["faces"] == len(rec.mesh.faces)
    assert set(sidecar["timings"]) >= {"preprocess_s", "train_s", "extract_s", "total_s"}
    counts = sidecar["counts"]
    assert counts["input_points"] == 4000 and counts["surface_points"] == 3000
    assert counts["queries"] == 3000 * 20 + 10_000
    assert counts["parameters"] == 64 * 5 + 64 * 66 * 2 + 66
    assert counts["faces"] == len(rec.mesh.faces)
    assert sidecar["config"]["train"]["iters"] == 400
    assert ultraboneudf.Config.from_dict(sidecar["config"]) == rec.config
    rec.save(tmp_path / "m.obj")
    assert (tmp_path / "m.obj").exists() and (tmp_path / "m.obj.json").exists()


def test_fit_issues_name_what_is_missing_or_unsupported(small_run):
    from ultraboneudf.cli.fit_hints import cli_text
    from ultraboneudf.pipeline import FitIssue

    rec = small_run
    assert rec.fit_issues(limit=1.0) == [] and rec.fit_warnings(limit=1.0) == []
    bad = dataclasses.replace(rec, data_fit={"threshold_mm": 3.0, "input_far_fraction": 0.097,
                                             "input_p95_mm": 37.0, "mesh_far_area_fraction": 0.21})
    far, loose = bad.fit_issues()
    # the data: what was measured, against which threshold, why, and what addresses it
    assert far == FitIssue("input_far", 0.097, 0.01, 3.0, "fit", retry=("seed", "preset"))
    assert (loose.kind, loose.value, loose.threshold, loose.distance_mm, loose.units) == \
        ("mesh_far", 0.21, 0.01, 3.0, "fraction")
    assert loose.cause == "unsupported" and loose.setting is None  # the trim is already on
    assert [i.kind for i in bad.fit_issues(limit=0.1)] == ["mesh_far"]
    # each front end phrases them for its users
    missing, unsupported = bad.fit_warnings()
    assert missing.startswith("9.7% of the input points are more than 3 mm from the mesh")
    assert unsupported.startswith("21.0% of the mesh area is 3 mm or more from every input point")
    assert unsupported.endswith("surface the data does not support") and cli_text(loose) == unsupported
    # the advice depends on the configuration that made the mesh
    for section, key, value, cli, python in (
            ("extract", "trim_mm", 0.0, "--set extract.trim_mm=3 removes it", "extract__trim_mm=3 removes it"),
            ("data", "bridge", 1.0, "--set data.bridge=0 leaves the gaps open", "data__bridge=0 leaves the gaps open")):
        cfg = ultraboneudf.Config.from_dict(rec.config.to_dict())
        setattr(getattr(cfg, section), key, value)
        issue = dataclasses.replace(bad, config=cfg).fit_issues()[1]
        assert issue.setting == (f"{section}.{key}", 3.0 if key == "trim_mm" else 0.0)
        assert cli_text(issue).endswith(cli)
        assert dataclasses.replace(bad, config=cfg).fit_warnings()[1].endswith(python)
    assert missing.endswith("try another seed= or preset=")
    assert cli_text(far).endswith("try another --seed or --preset")
    assert dataclasses.replace(rec, data_fit={}).fit_issues() == []


def test_a_mesh_that_misses_its_input_is_a_python_warning():
    """Half the cloud is a far-off patch the short run cannot cover: reconstruct() warns with the
    sentence of fit_warnings(), naming the source."""
    import warnings

    from ultraboneudf.errors import FitWarning

    pts = patch_points()
    far = pts[: len(pts) // 20] + np.array([0.0, 0.0, 400.0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = ultraboneudf.reconstruct(np.concatenate([pts, far]), preset="fast", device="cpu", seed=3,
                                       source="two patches", **SMALL)
    fits = [w for w in caught if issubclass(w.category, FitWarning)]
    assert [str(w.message) for w in fits] == [f"two patches: {t}" for t in rec.fit_warnings()]
    assert fits, rec.data_fit


def test_same_seed_same_mesh_on_cpu(small_run):
    again = ultraboneudf.reconstruct(patch_points(), preset="fast", device="cpu", seed=3, **SMALL)
    np.testing.assert_array_equal(again.mesh.vertices, small_run.mesh.vertices)
    np.testing.assert_array_equal(again.mesh.faces, small_run.mesh.faces)


def test_loss_decreases(small_run):
    tangent = small_run.history["tangent"]
    assert tangent[-1] < 0.5 * tangent[0]


def test_trained_field_can_be_extracted_again(small_run):
    """``Reconstruction.field`` is the unit-space field the mesh came from: extracting it again with
    the run's own settings gives the same mesh (mm), and it is small on the input points."""
    import torch

    rec = small_run
    again = rec.extract()
    np.testing.assert_allclose(again.vertices, rec.mesh.vertices, atol=1e-9)
    np.testing.assert_array_equal(again.faces, rec.mesh.faces)
    unit = torch.as_tensor(rec.normalizer.forward(patch_points(500, seed=9)), dtype=torch.float32)
    u = rec.field.value(unit)
    # the field's zero set lies on the patch: u at fresh surface samples is under one leaf cell
    assert float(u.abs().median()) < 2 / 2**7, float(u.abs().median())


def test_fit_then_extract_is_reconstruct(small_run):
    """``fit`` is the first half of ``reconstruct``: the same input, preset and seed give the same
    field, its extraction is the same mesh, and the fitted surface extracts again with other settings
    (coarser leaves: fewer faces) without training again."""
    import torch

    surface = ultraboneudf.fit(patch_points(), preset="fast", device="cpu", seed=3, **SMALL)
    assert surface.method == "ultraboneudf" and surface.config == small_run.config
    x = torch.rand(1000, 3) - 0.5
    torch.testing.assert_close(surface.field.value(x), small_run.field.value(x), rtol=0, atol=0)
    mesh = surface.extract()
    np.testing.assert_array_equal(mesh.faces, small_run.mesh.faces)
    np.testing.assert_allclose(mesh.vertices, small_run.mesh.vertices, atol=1e-9)
    coarse = small_run.surface.extract(max_depth=5)
    assert 0 < len(coarse.faces) < len(small_run.mesh.faces) / 2


def test_support_trim_keeps_only_faces_near_the_data(small_run):
    """``extract.trim_mm`` (3 mm in ``fast``) drops exactly the faces whose mean vertex distance to
    the voxelised input is ≥ 3 mm: every kept face is closer, the untrimmed extraction has the
    removed faces on top, and the sidecar counts them."""
    from scipy.spatial import cKDTree

    rec = small_run
    assert rec.config.extract.trim_mm == 3.0
    untrimmed = rec.extract(trim_mm=0)
    support_mm = rec.normalizer.inverse(rec.support)  # the voxelised input (0.1 mm voxels)
    assert cKDTree(patch_points()).query(support_mm)[0].max() < 0.1
    tree = cKDTree(support_mm)
    kept = tree.query(rec.mesh.vertices)[0][rec.mesh.faces].mean(axis=1)
    assert kept.max() < 3.0 + 1e-6, kept.max()
    dropped = tree.query(untrimmed.vertices)[0][untrimmed.faces].mean(axis=1) >= 3.0
    assert len(untrimmed.faces) - len(rec.mesh.faces) == rec.counts["trimmed_faces"] == dropped.sum()


def sweep_patch(seed=0, lost=(18.0, 22.5), frames=False):
    """The patch as a hard ultrasound sweep sees it from above (beam −z): slices y = const every
    1.5 mm with the run of slices between ``lost`` (mm; a 4.5 mm run) missing, points every 0.15 mm
    along x, 0.8 mm noise along the beam, 3% false echoes up to 10 mm under the surface; each
    point's probe 45 mm up its beam. With ``frames``, also each point's slice number."""
    rng = np.random.default_rng(seed)
    ys = np.arange(0.75, LENGTH, 1.5)
    ys = ys[(ys < lost[0]) | (ys > lost[1])]
    pts = []
    for y in ys:
        x = np.arange(-RADIUS * np.cos(np.pi / 4), RADIUS * np.cos(np.pi / 4), 0.15)
        z = np.sqrt(RADIUS**2 - x**2) + rng.normal(0, 0.8, len(x))
        echo = rng.random(len(x)) < 0.03
        z[echo] -= rng.uniform(0, 10, echo.sum())
        pts.append(np.c_[x, np.full_like(x, y), z])
    points = np.concatenate(pts)
    probe = points.copy()
    probe[:, 2] = 45.0
    if frames:
        return points, probe, np.repeat(np.arange(len(ys)), [len(p) for p in pts])
    return points, probe


def test_robust_preset_keeps_a_noisy_gappy_sweep_with_false_echoes_in_one_layer():
    """On that sweep the robust preset drops the false echoes (the sidecar counts them), removes the
    noise along the beam, bridges the missing run and the slices, and meshes one layer within
    0.3 mm (CD) of the truth: over the patch its area is within 10% of the patch's (measured: CD
    0.16 mm, 1.02), and past the patch's rims, where the data end, the surface goes on no further
    than the preset's 2 mm rim reach (plus half a leaf). ``fast`` on the same points (CD 1.35 mm,
    twice the area at 2,000 steps) doubles the surface under the false echoes."""
    points, probe = sweep_patch()
    rec = ultraboneudf.reconstruct(points, device="cpu", seed=3, probe_positions=probe,
                                   **{"train.iters": 1500})
    assert rec.preset == "robust"
    n_echoes = 0.03 * len(points)
    assert 0.5 * n_echoes < rec.counts["outliers_removed"] < 3 * n_echoes
    assert rec.counts["extract_depth"] == 6          # 80 mm domain: leaves ≥ 1 mm (1.25 mm)
    res = evaluate(rec.mesh, patch_mesh(), samples=200_000, seed=0)
    assert res.cd_mm < 0.3 and res.hd95_mm < 1.5, res
    centre = rec.mesh.triangles_center
    angle = np.degrees(np.abs(np.arctan2(centre[:, 0], centre[:, 2])))
    past_side = np.radians(np.maximum(angle - 45.0, 0.0)) * RADIUS
    past_end = np.maximum(np.maximum(-centre[:, 1], centre[:, 1] - LENGTH), 0.0)
    over = (past_side == 0) & (past_end == 0)
    assert 0.9 < rec.mesh.area_faces[over].sum() / patch_mesh().area < 1.1
    reach = rec.config.data.rim_reach * rec.config.data.surface_fit_mm
    assert max(past_side.max(), past_end.max()) < reach + 0.5 * 1.25
    assert rec.quality["nonmanifold_edges"] == 0


def test_a_sweep_with_its_frames_bridges_a_long_run_of_lost_frames():
    """Five slices lost (a 9 mm gap between the slices either side at y = 14.25 and 23.25 mm),
    longer than the ordinary bridge closes (4 mm planes). With each point's frame the robust preset
    bridges the run (``data.frame_bridge``: gaps across frames up to 10 mm): the surface it measures
    to passes within 1 mm of the bone over the run, and the mesh covers the run on the bone
    (measured: 1.06 of its area, 0.1 without the frames at its middle). Without the frames the
    surface ends 2 mm past each rim, and the middle of the run stays open."""
    points, probe, frames = sweep_patch(seed=1, lost=(15.0, 22.5), frames=True)

    def covered(mesh, lo, hi):  # mesh area over lo < y < hi, over the patch's own area there
        centre = mesh.triangles_center
        return mesh.area_faces[(centre[:, 1] > lo) & (centre[:, 1] < hi)].sum() / (np.pi / 2 * RADIUS * (hi - lo))

    angle = np.radians(np.linspace(-40.0, 40.0, 9))
    bone = np.array([[RADIUS * np.sin(t), y, RADIUS * np.cos(t)] for t in angle for y in (17.0, 18.75, 20.5)])

    def to_support(rec):  # mm from the bone over the run to the surface the trim measures to
        return rec.support.distance(rec.normalizer.forward(bone)) * rec.normalizer.scale

    kw = {"device": "cpu", "seed": 3, "probe_positions": probe, "train.iters": 1500}
    bridged = ultraboneudf.reconstruct(points, frame_index=frames, **kw)
    assert bridged.counts["frames"] == len(np.unique(frames)) == 22
    assert to_support(bridged).max() < 1.0
    assert 0.85 < covered(bridged.mesh, 16.25, 21.25) < 1.15
    on = bridged.mesh.triangles_center[np.abs(bridged.mesh.triangles_center[:, 1] - 18.75) < 2.5]
    assert np.median(np.abs(np.hypot(on[:, 0], on[:, 2]) - RADIUS)) < 0.5
    assert bridged.quality["nonmanifold_edges"] == 0
    plain = ultraboneudf.reconstruct(points, **kw)
    assert plain.counts["frames"] == 0
    assert to_support(plain).min() > 2.0
    assert covered(plain.mesh, 17.75, 19.75) < 0.3


def test_frame_indices_are_checked_against_the_points():
    points, probe, frames = sweep_patch(frames=True)
    with pytest.raises(InputError, match="frame indices need the probe positions"):
        ultraboneudf.reconstruct(points, device="cpu", frame_index=frames)
    with pytest.raises(InputError, match=r"frame indices must be N integers, one per point \(N = "):
        ultraboneudf.reconstruct(points, device="cpu", probe_positions=probe, frame_index=frames[:-1])
    with pytest.raises(InputError, match="frame indices must be N integers"):
        ultraboneudf.reconstruct(points, device="cpu", probe_positions=probe, frame_index=frames + 0.5)


def test_max_voxels_coarsens_the_voxel_until_the_cloud_fits():
    """40,000 points on the patch, at most 3,000 voxels: a coarser voxel is used, recorded in the
    sidecar counts, and the mesh still lies on the patch."""
    pts = patch_points(40_000, seed=4)
    rec = ultraboneudf.reconstruct(pts, preset="robust", device="cpu", seed=3,
                                   **{**SMALL, "data.max_voxels": 3_000})
    assert rec.counts["voxelized_points"] <= 3_000 < len(pts)
    assert rec.counts["voxel_size_mm"] > 0.1
    assert 4.0 <= rec.counts["plane_radius_mm"] <= 8.0  # data.surface_fit_mm, wider where sparse
    assert 0.4 <= rec.counts["trim_normal_mm"] <= 1.0  # extract.trim_normal_mm, nearer on a thin band
    radial = np.abs(np.hypot(rec.mesh.vertices[:, 0], rec.mesh.vertices[:, 2]) - RADIUS)
    assert np.median(radial) < 0.5
    plain = ultraboneudf.reconstruct(pts[:2_000], preset="fast", device="cpu", seed=3, **SMALL)
    assert plain.counts["voxel_size_mm"] == 0.1   # no limit: the voxel as configured
    assert plain.counts["plane_radius_mm"] == 0.0  # no local planes
    assert plain.counts["trim_normal_mm"] == 0.0


def test_a_sparse_cloud_gets_wider_planes_and_keeps_its_surface():
    """A clean plane of 0.25 points per mm² (12 within 4 mm): at the fixed 4 mm radius the local
    planes take 4% of it for isolated points or outliers; the robust preset widens the radius until
    the median point has 36 within it, and keeps all but a few of them. The radius used is reported."""
    from ultraboneudf.config.presets import preset
    from ultraboneudf.preprocess import prepare

    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-60.0, 60.0, (3600, 2)), rng.normal(0.0, 0.3, 3600)]
    fixed = preset("robust")
    fixed.data.surface_fit_points = 0
    _, narrow = prepare(pts, fixed, seed=0)
    _, wide = prepare(pts, preset("robust"), seed=0)
    assert narrow.plane_radius_mm == 4.0 and narrow.outliers > 0.03 * len(pts)
    assert 6.0 < wide.plane_radius_mm < 7.5  # 4 mm × √(36 / 12)
    assert wide.outliers < 0.01 * len(pts)
    assert wide.planes.base == pytest.approx(wide.plane_radius_mm / wide.normalizer.scale)


def test_configure_gives_the_complete_configuration_reconstruct_takes_as_it_is(small_run):
    """configure() applies the method's defaults and the overrides once; handed to
    reconstruct(config=...) it is used as it is: the same configuration, and the same mesh, as the
    preset and overrides given to reconstruct; the caller's config is not changed."""
    from ultraboneudf.pipeline import configure

    cfg = configure("fast", "ultraboneudf", SMALL)
    assert cfg == small_run.config
    before = ultraboneudf.Config.from_dict(cfg.to_dict())
    rec = ultraboneudf.reconstruct(patch_points(), preset="fast", config=cfg, device="cpu", seed=3)
    assert rec.config == small_run.config and rec.preset == "fast" and cfg == before
    np.testing.assert_array_equal(rec.mesh.vertices, small_run.mesh.vertices)
    np.testing.assert_array_equal(rec.mesh.faces, small_run.mesh.faces)
    # a method's defaults are applied by configure, not again by reconstruct
    capudf = configure("robust", "capudf", assignments=["train.iters=30"])
    assert capudf.grid.resolution == 128 and capudf.train.iters == 30
    assert configure(config=capudf) == capudf and configure(config=capudf) is not capudf
    assert configure("robust", "capudf", config=capudf, overrides={"train.iters": 40}).train.iters == 40
    with pytest.raises(InputError, match="method funsr cannot checkpoint its training"):
        configure("fast", "funsr", checkpoint=True)


def test_the_extract_margin_covers_how_far_above_zero_the_field_stays_on_its_points():
    """Points on the plane z = 0.01 under the field |z| (the field stays 0.01 above zero on all of
    them, as one trained on a thick sparse band does between its points): the margin rises to
    ``data_margin`` × 0.01; on points where the field is zero it stays ``extract.margin``, and
    ``data_margin`` = 0 or a method without a field leaves it as given."""
    from ultraboneudf.config import ExtractConfig
    from ultraboneudf.fields.analytic import PlaneUDF
    from ultraboneudf.pipeline import resolve_margin

    rng = np.random.default_rng(0)
    on = np.c_[rng.uniform(-0.5, 0.5, (500, 2)), np.zeros(500)]
    above = on + [0.0, 0.0, 0.01]
    cfg = ExtractConfig(margin=0.002, data_margin=1.25)
    field = PlaneUDF()
    assert resolve_margin(cfg, field, above).margin == pytest.approx(0.0125)
    assert resolve_margin(dataclasses.replace(cfg, data_margin=0.5), field, above).margin == pytest.approx(0.005)
    assert resolve_margin(cfg, field, on).margin == 0.002
    assert resolve_margin(dataclasses.replace(cfg, data_margin=0.0), field, above).margin == 0.002
    assert resolve_margin(cfg, None, above).margin == 0.002


def test_the_normal_trim_follows_the_spread_of_the_band():
    """Bands of points about the plane z = 0, σ = 0.05 / 0.2 / 0.5 mm: the robust preset's normal
    trim is 3 σ (their planes' median spread) where that is under ``trim_normal_mm`` (1 mm), never
    under 0.4 mm; in unit space (scale 100 mm per unit) the same. A sheet 0.6 mm over the thinnest
    band is trimmed away with it and kept by the fixed 1 mm; ``trim_normal_sigmas`` = 0 or no planes
    leave the trim as given."""
    from ultraboneudf.config.presets import preset
    from ultraboneudf.extraction import trim_to_support
    from ultraboneudf.geometry.data_surface import DataSurface
    from ultraboneudf.geometry.surface_fit import fit_local_planes
    from ultraboneudf.pipeline import resolve_normal_trim

    cfg = preset("robust").extract
    assert (cfg.trim_normal_mm, cfg.trim_normal_sigmas) == (1.0, 3.0)
    rng = np.random.default_rng(0)
    trims = {}
    for sigma in (0.05, 0.2, 0.5):
        pts = np.c_[rng.uniform(-30.0, 30.0, (6000, 2)), rng.normal(0.0, sigma, 6000)]
        planes = fit_local_planes(pts, 4.0)
        trims[sigma] = resolve_normal_trim(cfg, planes, 1.0).trim_normal_mm
        unit = resolve_normal_trim(cfg, planes.scaled(0.01), 100.0).trim_normal_mm
        assert unit == pytest.approx(trims[sigma])
    assert trims[0.05] == 0.4
    assert trims[0.2] == pytest.approx(0.6, abs=0.05)
    assert trims[0.5] == 1.0
    assert resolve_normal_trim(dataclasses.replace(cfg, trim_normal_sigmas=0.0), planes, 1.0).trim_normal_mm == 1.0
    assert resolve_normal_trim(cfg, None, 1.0).trim_normal_mm == 1.0

    pts = np.c_[rng.uniform(-30.0, 30.0, (6000, 2)), rng.normal(0.0, 0.05, 6000)]
    planes = fit_local_planes(pts, 4.0)
    surface = DataSurface.from_planes(pts, planes, bridge=4.0)
    sheet = trimesh.creation.box(extents=(40.0, 40.0, 1.2))  # faces at z = ±0.6 and its sides
    sheet = trimesh.Trimesh(sheet.vertices, sheet.faces[np.abs(sheet.triangles_center[:, 2] - 0.6) < 1e-9])
    assert trim_to_support(sheet, surface, 3.0, max_normal=1.0) is sheet
    trim = resolve_normal_trim(cfg, planes, 1.0).trim_normal_mm
    assert trim_to_support(sheet, surface, 3.0, max_normal=trim) is None


def test_with_the_data_margin_the_extractor_meshes_a_field_that_stays_above_zero_on_its_points():
    """|z| + 0.03 never reaches zero (a field trained on a thick sparse band stays above zero
    between its points): with the reference margin the robust preset's extractor finds no surface
    at depth 6 (leaf edge 0.031); with the margin raised to 1.25 × the field at the points on z = 0
    it meshes the plane z = 0 across the domain (area 4, within 0.02 of it), within half a leaf."""
    from ultraboneudf.extraction import extract_mesh
    from ultraboneudf.fields.base import Field
    from ultraboneudf.pipeline import resolve_margin

    class Lifted(Field):
        def _value(self, x):
            return x[:, 2].abs() + 0.03

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.9, 0.9, (400, 2)), np.zeros(400)]
    cfg = dataclasses.replace(ultraboneudf.config.preset("robust").extract, max_depth=6, min_leaf_mm=0.0)
    assert extract_mesh(Lifted(), dataclasses.replace(cfg, data_margin=0.0)) is None
    raised = resolve_margin(cfg, Lifted(), points)
    assert raised.margin == pytest.approx(1.25 * 0.03)
    mesh = extract_mesh(Lifted(), raised)
    assert mesh is not None and abs(mesh.area - 4.0) < 0.02, None if mesh is None else mesh.area
    assert np.abs(mesh.vertices[:, 2]).max() < 0.5 * 2.0 / 2**6  # within half a leaf of z = 0


def test_a_cloud_written_frame_by_frame_row_by_row_tells_its_beams():
    """The mask pixels of a shaft's upper arc, 15 frames listed row by row from the probe down (as a
    compounding writes them): the robust preset takes the beams of all 15 for the false echoes'
    side and the grazing trim; the same cloud in another order, or with the option off, tells none;
    with probe positions the beams are theirs."""
    import sys
    from pathlib import Path

    from ultraboneudf.config.presets import preset
    from ultraboneudf.preprocess import prepare

    sys.path.insert(0, str(Path(__file__).parent / "geometry"))
    from test_frame_order import mask_frames

    frames, beam = mask_frames()
    pts = np.concatenate(frames)
    _, unit = prepare(pts, preset("robust"), seed=0)
    assert unit.order_frames == len(frames)
    # the kept points carry them on to the grazing trim, unit length
    assert len(unit.beams) == len(unit.points) and np.all(unit.beams @ beam > np.cos(np.radians(1.0)))
    shuffled = pts[np.random.default_rng(0).permutation(len(pts))]
    assert prepare(shuffled, preset("robust"), seed=0)[1].order_frames == 0
    off = preset("robust")
    off.data.beams_from_order = False
    assert prepare(pts, off, seed=0)[1].order_frames == 0
    assert prepare(pts, off, seed=0)[1].beams is None
    # a sweep's beams come from its probe positions
    probe = pts + 30.0 * np.array([0.0, 0.0, 1.0])
    swept = prepare(pts, preset("robust"), seed=0, probe_positions=probe)[1]
    assert swept.order_frames == 0 and np.all(swept.beams @ beam > np.cos(np.radians(1.0)))


def test_the_extraction_trims_the_faces_along_the_beams_the_cloud_told():
    """The shaft's arc of :func:`test_a_cloud_written_frame_by_frame_row_by_row_tells_its_beams`
    (beams −z), and a mesh in unit space: a patch on the shaft's top (the beams meet it head-on)
    and a wall standing beside it along the beams. With ``extract.trim_grazing_deg`` the wall goes
    and the patch stays; at 0 both stay."""
    import dataclasses
    import sys
    from pathlib import Path

    import trimesh

    from ultraboneudf.config.presets import preset
    from ultraboneudf.pipeline import _trim_and_map
    from ultraboneudf.preprocess import prepare

    sys.path.insert(0, str(Path(__file__).parent / "geometry"))
    from test_frame_order import mask_frames

    frames, _ = mask_frames()
    cfg = preset("robust")
    _, unit = prepare(np.concatenate(frames), cfg, seed=0)
    patch = trimesh.creation.box(extents=(20.0, 4.0, 1e-3))
    patch.apply_translation([0.0, 0.0, 12.0])
    wall = trimesh.creation.box(extents=(20.0, 1e-3, 3.0))
    wall.apply_translation([0.0, 3.0, 10.5])
    mesh = trimesh.util.concatenate([patch, wall])
    unit_mesh = trimesh.Trimesh(unit.normalizer.forward(mesh.vertices), mesh.faces, process=False)
    extract = dataclasses.replace(cfg.extract, trim_mm=0.0, trim_normal_mm=0.0, trim_rim_mm=0.0)
    out, removed = _trim_and_map(unit_mesh, unit.points, unit.normalizer, extract, unit)
    assert removed > 0 and np.abs(out.face_normals[:, 1]).max() < 0.5  # no face of the wall's sides
    assert out.area > patch.area * 0.99
    kept, removed = _trim_and_map(unit_mesh, unit.points, unit.normalizer,
                                  dataclasses.replace(extract, trim_grazing_deg=0.0), unit)
    assert removed == 0 and kept.area == pytest.approx(mesh.area)
