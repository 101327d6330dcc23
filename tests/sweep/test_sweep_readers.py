"""Sweep readers and writers: round trips (transforms equal to 1e-9), layout detection, masks,
PLUS/Slicer conventions, and the real UltraBones100k sample."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from ultraboneudf.errors import InputError
from ultraboneudf.sweep import Sweep, SweepWarning, detect_layout, is_sweep_path, read_sweep, write_sweep
from ultraboneudf.sweep.formats import metaio, nrrd_seq, ultrabones
from ultraboneudf.sweep.formats.images import load_mask_stack, write_png
from ultraboneudf.sweep.transforms import rigid_from_euler

SAMPLE = Path(__file__).resolve().parents[3] / "shared" / "data" / "ultrabones100k_sample"


def make_sweep(n=5, w=12, h=9, spacing=(0.2, 0.2), offset=0.5, seed=0, masks=True) -> Sweep:
    rng = np.random.default_rng(seed)
    poses = np.stack([rigid_from_euler(rng.uniform(-300, 300, 3),
                                       rng.uniform([-170, -80, -170], [170, 80, 170])) for _ in range(n)])
    images = rng.integers(0, 256, size=(n, h, w), dtype=np.uint8)
    m = rng.random((n, h, w)) < 0.1 if masks else None
    return Sweep(image_to_world=poses, spacing_mm=spacing, image_size=(w, h), images=images, masks=m,
                 timestamps=np.arange(n) * 40.0 + 1000, pixel_offset=offset)


def assert_same_geometry(a: Sweep, b: Sweep):
    assert a.n_frames == b.n_frames
    np.testing.assert_allclose(a.pixel_to_world(), b.pixel_to_world(), rtol=0, atol=1e-9)


@pytest.mark.parametrize("offset", [0.5, 0.0])
def test_ultrabones_round_trip(tmp_path, offset):
    s = make_sweep(offset=offset)
    calib = rigid_from_euler([26.4, -0.5, 128.0], [92.5, -0.47, 179.2])
    ultrabones.write(s, tmp_path / "sw", calibration=calib)
    r = read_sweep(tmp_path / "sw")
    assert_same_geometry(s, r)
    np.testing.assert_array_equal(r.images, s.images)
    np.testing.assert_array_equal(r.masks, s.masks)
    np.testing.assert_array_equal(r.timestamps, s.timestamps)
    np.testing.assert_allclose(r.meta["calibration"], calib, atol=1e-12)


def test_ultrabones_anisotropic_spacing_goes_to_calibration(tmp_path):
    s = make_sweep(spacing=(0.1, 0.3), masks=False)
    ultrabones.write(s, tmp_path / "sw")
    header = (tmp_path / "sw" / "poses.csv").read_text().splitlines()[0]
    assert "space_factor" not in header
    assert_same_geometry(s, read_sweep(tmp_path / "sw"))


def test_ultrabones_masks_only_and_mask_dir(tmp_path):
    s = make_sweep()
    ultrabones.write(s, tmp_path / "sw", write_images=False, mask_sets={"pred": ~s.masks})
    r = read_sweep(tmp_path / "sw")
    assert r.images is None
    np.testing.assert_array_equal(r.masks, s.masks)
    r2 = read_sweep(tmp_path / "sw", mask_dir="pred")
    np.testing.assert_array_equal(r2.masks, ~s.masks)


def test_masks_as_numpy_array(tmp_path):
    s = make_sweep(masks=False)
    ultrabones.write(s, tmp_path / "sw")
    masks = np.zeros((s.n_frames, s.height, s.width), dtype=np.uint8)
    masks[:, 4, 2:7] = 1
    np.save(tmp_path / "sw" / "masks.npy", masks)
    r = read_sweep(tmp_path / "sw")
    np.testing.assert_array_equal(r.masks, masks != 0)
    # and given explicitly, for a PLUS file with the same poses
    metaio.write(s, tmp_path / "a.mha")
    r = read_sweep(tmp_path / "a.mha", masks=tmp_path / "sw" / "masks.npy")
    np.testing.assert_array_equal(r.masks, masks != 0)


def test_mask_png_stack_matched_by_order(tmp_path):
    masks = np.zeros((3, 4, 5), dtype=bool)
    masks[1, 2, 3] = True
    for i, name in enumerate(["b", "c", "d"]):
        write_png(tmp_path / "m" / f"{name}.png", masks[i])
    out = load_mask_stack(tmp_path / "m", 3, (5, 4), ["x", "y", "z"])
    np.testing.assert_array_equal(out, masks)
    with pytest.raises(InputError, match="2 frames"):
        load_mask_stack(tmp_path / "m", 2, (5, 4))


@pytest.mark.parametrize("name, kw", [("a.mha", {}), ("b.mhd", {}), ("c.mhd", {"compress": True}),
                                      ("d.mha", {"compress": True})])
def test_metaio_round_trip(tmp_path, name, kw):
    s = make_sweep()
    metaio.write(s, tmp_path / name, **kw)
    r = read_sweep(tmp_path / name)
    assert_same_geometry(s, r)
    assert r.pixel_offset == 0.0
    np.testing.assert_array_equal(r.images, s.images)
    np.testing.assert_array_equal(r.timestamps, s.timestamps)


def test_metaio_masks_as_data(tmp_path):
    s = make_sweep()
    metaio.write(s, tmp_path / "m.mha", data="masks")
    r = read_sweep(tmp_path / "m.mha", as_masks=True)
    np.testing.assert_array_equal(r.masks, s.masks)
    assert r.images is None


@pytest.mark.parametrize("list_axis", ["last", "first"])
def test_nrrd_round_trip(tmp_path, list_axis):
    s = make_sweep(spacing=(0.15, 0.25))
    nrrd_seq.write(s, tmp_path / "s.seq.nrrd", list_axis=list_axis)
    r = read_sweep(tmp_path / "s.seq.nrrd")
    assert_same_geometry(s, r)
    np.testing.assert_array_equal(r.images, s.images)
    np.testing.assert_array_equal(r.timestamps, s.timestamps)


def test_nrrd_with_transforms_in_a_companion_metafile(tmp_path):
    import nrrd

    s = make_sweep()
    metaio.write(s, tmp_path / "t.mha")
    vol = np.transpose(s.images, (2, 1, 0))[:, :, None, :]  # W H 1 F
    nrrd.write(str(tmp_path / "img.seq.nrrd"), vol, {"kinds": ["domain", "domain", "domain", "list"]})
    with pytest.raises(InputError, match="no per-frame transforms"):
        read_sweep(tmp_path / "img.seq.nrrd")
    r = read_sweep(tmp_path / "img.seq.nrrd", transforms=tmp_path / "t.mha")
    assert_same_geometry(s, r)


def _mha_text(frames: int, transform_lines: list[str], extra: str = "", w=3, h=2) -> bytes:
    head = (f"ObjectType = Image\nNDims = 3\nDimSize = {w} {h} {frames}\nElementType = MET_UCHAR\n"
            + extra + "".join(line + "\n" for line in transform_lines) + "ElementDataFile = LOCAL\n")
    return head.encode() + bytes(range(w * h * frames))


def _m(scale=0.1, tx=0.0):
    return f"{scale} 0 0 {tx} 0 {scale} 0 0 0 0 {scale} 0 0 0 0 1"


def test_metaio_skips_invalid_frames_and_tolerates_duplicates(tmp_path):
    lines = [f"Seq_Frame0000_ImageToReferenceTransform = {_m(tx=1)}",
             f"Seq_Frame0001_ImageToReferenceTransform = {_m(tx=2)}",
             "Seq_Frame0001_ImageToReferenceTransformStatus = INVALID",
             f"Seq_Frame0002_ImageToReferenceTransform = {_m(tx=3)}",
             "Seq_Frame0002_Timestamp = 7.5", "Seq_Frame0002_Timestamp = 8.5"]
    path = tmp_path / "x.mha"
    path.write_bytes(_mha_text(3, lines, "UltrasoundImageOrientation = MF\n"))
    with pytest.warns(SweepWarning) as rec:
        s = read_sweep(path)
    messages = " ".join(str(r.message) for r in rec)
    assert "INVALID" in messages and "duplicated" in messages
    assert s.n_frames == 2
    np.testing.assert_allclose(s.image_to_world[:, 0, 3], [1, 3])
    np.testing.assert_allclose(s.spacing_mm, 0.1)
    assert s.timestamps[1] == 8.5
    np.testing.assert_array_equal(s.images[1].ravel(), np.arange(12, 18))


@pytest.mark.parametrize("orientation, flip", [("UF", (slice(None), slice(None, None, -1))),
                                               ("MN", (slice(None, None, -1), slice(None))),
                                               ("UN", (slice(None, None, -1), slice(None, None, -1)))])
def test_metaio_orientation_flipped_to_mf(tmp_path, orientation, flip):
    path = tmp_path / "o.mha"
    path.write_bytes(_mha_text(1, [f"Seq_Frame0000_ImageToReferenceTransform = {_m()}"],
                               f"UltrasoundImageOrientation = {orientation}\n"))
    s = read_sweep(path)
    stored = np.arange(6, dtype=np.uint8).reshape(2, 3)
    np.testing.assert_array_equal(s.images[0], stored[flip])


def test_metaio_probe_transform_with_calibration(tmp_path):
    cal = np.diag([0.1, 0.1, 0.1, 1.0])
    probe = rigid_from_euler([5, 6, 7], [10, 20, 30])
    line = "Seq_Frame0000_ProbeToTrackerTransform = " + " ".join(repr(float(v)) for v in probe.ravel())
    path = tmp_path / "p.mha"
    path.write_bytes(_mha_text(1, [line], "UltrasoundImageOrientation = MF\n"))
    with pytest.raises(InputError, match="no per-frame ImageTo"):
        read_sweep(path)
    with pytest.warns(SweepWarning, match="Tracker .camera. frame"):   # no ReferenceToTracker here
        s = read_sweep(path, image_to_probe=cal)
    np.testing.assert_allclose(s.pixel_to_world()[0][:, [0, 1, 3]], (probe @ cal)[:, [0, 1, 3]], atol=1e-12)


def test_layout_detection(tmp_path):
    s = make_sweep()
    write_sweep(s, tmp_path / "folder")
    write_sweep(s, tmp_path / "a.mha")
    write_sweep(s, tmp_path / "a.seq.nrrd")
    assert detect_layout(tmp_path / "folder") == "ultrabones"
    assert detect_layout(tmp_path / "a.mha") == "metaio"
    assert detect_layout(tmp_path / "a.seq.nrrd") == "nrrd"
    assert is_sweep_path(tmp_path / "folder") and not is_sweep_path(tmp_path / "a.xyz")
    (tmp_path / "a.xyz").write_text("0 0 0\n")
    with pytest.raises(InputError, match="unknown sweep format"):
        read_sweep(tmp_path / "a.xyz")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="not a sweep folder"):
        read_sweep(tmp_path / "empty")


def test_reading_never_modifies_input(tmp_path):
    s = make_sweep()
    write_sweep(s, tmp_path / "f")
    before = {p: p.read_bytes() for p in (tmp_path / "f").rglob("*") if p.is_file()}
    read_sweep(tmp_path / "f")
    after = {p: p.read_bytes() for p in (tmp_path / "f").rglob("*") if p.is_file()}
    assert before == after


@pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} not present")
def test_real_sample_chain_matches_readme():
    from scipy.spatial.transform import Rotation

    s = read_sweep(SAMPLE)
    assert s.n_frames == 30 and s.image_size == (950, 811) and s.images.dtype == np.uint8
    cal = json.loads((SAMPLE / "calibration.json").read_text())
    row = (SAMPLE / "poses.csv").read_text().splitlines()[3].split(",")
    ts, sf, x, y, z, ex, ey, ez = row[0], *map(float, row[1:])

    def rigid(t, e):
        m = np.eye(4)
        m[:3, :3] = Rotation.from_euler("xyz", e, degrees=True).as_matrix()
        m[:3, 3] = t
        return m

    chain = rigid([x, y, z], [ex, ey, ez]) @ rigid(cal["translation_mm"], cal["euler_xyz_deg"]) \
        @ np.diag([sf, sf, 1, 1])
    c, r = 400, 250
    expected = chain @ [c + 0.5, r + 0.5, 0, 1]
    i = s.frame_names.index(f"{ts}.png")
    got = s.pixel_to_world()[i] @ [c, r, 0, 1]
    np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} not present")
def test_real_sample_round_trips_through_every_format(tmp_path):
    s = read_sweep(SAMPLE).subset([0, 7, 29])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name in ("u", "s.mha", "s.seq.nrrd"):
            write_sweep(s, tmp_path / name)
            r = read_sweep(tmp_path / name)
            assert_same_geometry(s, r)
            np.testing.assert_array_equal(r.images, s.images)
