"""The PLUS pose chain: calibration files, chain resolution (hand-computed products), crops,
sheared and anisotropic calibrations, orientation codes, PLUS NRRD and 3D Slicer sequence files,
and the command line's sweep options."""

import warnings
from pathlib import Path

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.errors import InputError
from ultraboneudf.sweep import SweepWarning, read_sweep
from ultraboneudf.sweep.calibration import read_calibration
from ultraboneudf.sweep.chain import split_transform_name
from ultraboneudf.sweep.transforms import decompose_pixel_transform, format_matrix, rigid_from_euler

W, H, N = 6, 5, 4


def sheared_calibration(sx=0.08, sy=0.07, shear_deg=2.0, sz=0.075):
    """An ImageToProbe as PLUS calibrations are: per-axis scale, a little shear, any z scale."""
    r = rigid_from_euler([12.7, 50.8, -0.5], [3, -91, 2])
    phi = np.radians(shear_deg)
    a = np.array([[sx, sy * np.sin(phi), 0, 0], [0, sy * np.cos(phi), 0, 0], [0, 0, sz, 0], [0, 0, 0, 1]])
    return r @ a


def probe_poses(n=N):
    return [rigid_from_euler([100 + 2 * i, -50 + i, 30 - 0.5 * i], [10 + i, -20, 30 + 2 * i]) for i in range(n)]


def reference_poses(n=N):
    return [rigid_from_euler([300, -80, -50 + 0.1 * i], [-40, 5, 170 + 0.2 * i]) for i in range(n)]


def write_mha(path: Path, transforms: dict[str, list[np.ndarray]], n=N, w=W, h=H,
              orientation="MF", status: dict[str, list[str]] | None = None, pixels=None) -> Path:
    lines = ["ObjectType = Image", "NDims = 3", f"DimSize = {w} {h} {n}", "ElementType = MET_UCHAR"]
    if orientation is not None:
        lines.append(f"UltrasoundImageOrientation = {orientation}")
    for i in range(n):
        for name, mats in transforms.items():
            lines.append(f"Seq_Frame{i:04d}_{name}Transform = {format_matrix(mats[i])}")
            st = (status or {}).get(name)
            lines.append(f"Seq_Frame{i:04d}_{name}TransformStatus = {st[i] if st else 'OK'}")
        lines.append(f"Seq_Frame{i:04d}_Timestamp = {10 + 0.1 * i}")
    lines.append("ElementDataFile = LOCAL")
    data = pixels if pixels is not None else np.arange(n * h * w, dtype=np.uint8).reshape(n, h, w)
    path.write_bytes(("\n".join(lines) + "\n").encode() + np.ascontiguousarray(data, np.uint8).tobytes())
    return path


def write_config(path: Path, cal: np.ndarray, extra: str = "", volume: str = "") -> Path:
    m = " ".join(repr(float(v)) for v in cal.ravel())
    path.write_text(f"""<PlusConfiguration version="2.3">
  <CoordinateDefinitions>
    <Transform From="Image" To="Probe" Matrix="{m}" Error="0.58" Date="2012.02.06"/>
    {extra}
  </CoordinateDefinitions>
  <VolumeReconstruction OutputSpacing="0.5 0.5 0.5" {volume}/>
</PlusConfiguration>
""")
    return path


def hand(chain: list[np.ndarray], c: float, r: float) -> np.ndarray:
    m = np.eye(4)
    for t in chain:
        m = m @ t
    return (m @ [c, r, 0.0, 1.0])[:3]


def world(sweep, k: int, c: float, r: float) -> np.ndarray:
    return (sweep.pixel_to_world()[k] @ [c, r, 0.0, 1.0])[:3]


@pytest.mark.parametrize("name, pair", [
    ("ProbeToTracker", ("Probe", "Tracker")), ("ToolToTracker", ("Tool", "Tracker")),
    ("ImageToCroppedImageTransform", ("Image", "CroppedImage")), ("ProbeToReference-Seq", ("Probe", "Reference")),
    ("Unknown1ToUnknown2", ("Unknown1", "Unknown2")), ("Tracker", None), ("AToBToC", None),
])
def test_transform_names_split_as_plus_does(name, pair):
    assert split_transform_name(name) == pair


def test_decompose_sheared_anisotropic_calibration():
    cal = sheared_calibration(0.0854, 0.079, -2.745, 0.0822)
    part = decompose_pixel_transform(cal, "cal.xml")
    np.testing.assert_allclose(part.spacing_mm, [0.0854, 0.079], rtol=1e-12)
    assert part.shear_deg == pytest.approx(-2.745, abs=1e-9)
    r = part.rigid[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    with pytest.raises(InputError, match=r"cal.xml: .*sheared by 7.00°, tolerance 5°"):
        decompose_pixel_transform(sheared_calibration(shear_deg=7.0), "cal.xml")
    with pytest.raises(InputError, match="mirrored"):
        decompose_pixel_transform(sheared_calibration() @ np.diag([1, 1, -1, 1]), "cal.xml")


def test_chain_reference_tracker_probe_calibration(tmp_path):
    cal, probe, ref = sheared_calibration(), probe_poses(), reference_poses()
    mha = write_mha(tmp_path / "s.igs.mha", {"ProbeToTracker": probe, "ReferenceToTracker": ref,
                                             "StylusToTracker": [np.eye(4)] * N},
                    status={"StylusToTracker": ["INVALID"] * N})
    cfg = write_config(tmp_path / "cfg.xml", cal)
    s = read_sweep(mha, calibration=cfg)
    assert s.n_frames == N and s.meta["transform"] == "ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe"
    assert s.meta["chain"]["reference_frame"] == "Reference"
    for k in range(N):
        for c, r in [(0, 0), (5, 4), (2.5, 1)]:
            np.testing.assert_allclose(world(s, k, c, r), hand([np.linalg.inv(ref[k]), probe[k], cal], c, r),
                                       atol=1e-9)
    np.testing.assert_allclose(s.spacing_mm, [[0.08, 0.07]] * N, rtol=1e-12)
    np.testing.assert_allclose(s.shear_deg, 2.0, atol=1e-9)
    # the beam runs down the scan lines, which the shear tilts off the rigid y axis
    lateral, beam, normal = s.probe_axes()
    p2w = s.pixel_to_world()
    np.testing.assert_allclose(beam[0], p2w[0, :3, 1] / np.linalg.norm(p2w[0, :3, 1]), atol=1e-12)
    # the same with the calibration as a bare matrix file (16 numbers, commas and a comment)
    txt = tmp_path / "ImageToProbe.txt"
    txt.write_text("# ImageToProbe\n" + "\n".join(", ".join(repr(float(v)) for v in row) for row in cal))
    np.testing.assert_allclose(read_sweep(mha, calibration=txt).pixel_to_world(), s.pixel_to_world(), atol=1e-12)
    np.save(tmp_path / "cal.npy", cal)
    np.testing.assert_allclose(read_sweep(mha, calibration=tmp_path / "cal.npy").pixel_to_world(),
                               s.pixel_to_world(), atol=1e-12)
    # --reference Tracker: the probe chain alone; --transform must be in the chain
    t = read_sweep(mha, calibration=cfg, reference="Tracker")
    np.testing.assert_allclose(world(t, 1, 3, 2), hand([probe[1], cal], 3, 2), atol=1e-9)
    with pytest.raises(InputError, match="no per-frame ImageToReferenceTransform"):
        read_sweep(mha, calibration=cfg, transform="ImageToReference")


def test_direct_image_to_reference_wins_and_invalid_frames_are_skipped(tmp_path):
    cal, probe, ref = sheared_calibration(shear_deg=0.0), probe_poses(), reference_poses()
    direct = [np.linalg.inv(ref[i]) @ probe[i] @ cal @ rigid_from_euler([0, 0, 1.0], [0, 0, 0]) for i in range(N)]
    mha = write_mha(tmp_path / "d.mha", {"ImageToReference": direct, "ProbeToTracker": probe,
                                         "ReferenceToTracker": ref},
                    status={"ImageToReference": ["OK", "INVALID", "OK", "OK"]})
    with pytest.warns(SweepWarning, match="skipped 1 frame"):
        s = read_sweep(mha, calibration=write_config(tmp_path / "c.xml", cal))
    assert s.meta["transform"] == "ImageToReference" and s.n_frames == 3
    assert s.frame_names == ["Seq_Frame0000", "Seq_Frame0002", "Seq_Frame0003"]
    np.testing.assert_allclose(world(s, 1, 4, 3), hand([direct[2]], 4, 3), atol=1e-9)
    # forcing the tracking chain instead
    t = read_sweep(mha, calibration=tmp_path / "c.xml", transform="ProbeToTracker")
    np.testing.assert_allclose(world(t, 1, 4, 3), hand([np.linalg.inv(ref[1]), probe[1], cal], 4, 3), atol=1e-9)


def test_crop_offset_is_never_a_pose(tmp_path):
    cal, probe, ref = sheared_calibration(), probe_poses(), reference_poses()
    crop = np.eye(4)
    crop[:2, 3] = [-335, -285]
    transforms = {"ImageToCroppedImage": [crop] * N, "ProbeToTracker": probe, "ReferenceToTracker": ref}
    mha = write_mha(tmp_path / "crop.igs.mha", transforms)
    with pytest.raises(InputError, match="ImageToProbe is missing"):
        read_sweep(mha)
    s = read_sweep(mha, calibration=write_config(tmp_path / "c.xml", cal, volume='ClipRectangleOrigin="337 286" ClipRectangleSize="3 2"'))
    assert s.meta["chain"]["pixel_frame"] == "CroppedImage"
    assert s.meta["clip_rectangle_px"] == [2, 1, 3, 2]          # the clip moved into the crop
    # a cropped pixel (c, r) is the full image's pixel (c + 335, r + 285)
    np.testing.assert_allclose(world(s, 2, 1, 3), hand([np.linalg.inv(ref[2]), probe[2], cal], 336, 288), atol=1e-9)
    # only the offset: the frames would all share one pose
    only = write_mha(tmp_path / "only.mha", {"ImageToCroppedImage": [crop] * N})
    with pytest.raises(InputError, match="no per-frame tracking transform|no transform starts|no chain"):
        read_sweep(only, calibration=tmp_path / "c.xml")


def test_frames_with_one_pose_and_coplanar_frames(tmp_path, capsys):
    m = np.diag([0.1, 0.1, 1.0, 1.0])
    same = write_mha(tmp_path / "same.mha", {"ImageToReference": [m] * N})
    with pytest.raises(InputError, match="all 4 frames have the same pose"):
        read_sweep(same)
    slide = []
    for i in range(N):
        t = m.copy()
        t[0, 3] = 0.7 * i              # the probe slides within its own image plane
        slide.append(t)
    flat = write_mha(tmp_path / "flat.mha", {"ImageToReference": slide})
    with pytest.warns(SweepWarning, match="one plane"):
        read_sweep(flat)
    out = tmp_path / "p.ply"
    assert main(["sweep2points", str(flat), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flat.mha" in err[0] and "one plane" in err[0] and not out.exists()


ORIENTATIONS = [("MF", False, False), ("MN", False, True), ("UF", True, False), ("UN", True, True)]


@pytest.mark.parametrize("code, flip_cols, flip_rows", ORIENTATIONS)
@pytest.mark.parametrize("suffix", ["", "A", "D"])
def test_every_orientation_code_is_flipped_to_mf(tmp_path, code, flip_cols, flip_rows, suffix):
    pixels = np.arange(N * H * W, dtype=np.uint8).reshape(N, H, W)
    p = write_mha(tmp_path / "o.mha", {"ProbeToTracker": probe_poses(), "ReferenceToTracker": reference_poses()}, orientation=code + suffix, pixels=pixels)
    s = read_sweep(p, calibration=write_config(tmp_path / "c.xml", sheared_calibration()))
    want = pixels[:, ::-1 if flip_rows else 1, ::-1 if flip_cols else 1]
    np.testing.assert_array_equal(s.images, want)
    assert s.meta["file_orientation"] == code + suffix


def test_orientation_codes_not_b_mode(tmp_path):
    cfg = write_config(tmp_path / "c.xml", sheared_calibration())
    with pytest.raises(InputError, match="RF-mode"):
        read_sweep(write_mha(tmp_path / "rf.mha", {"ProbeToTracker": probe_poses(), "ReferenceToTracker": reference_poses()}, orientation="FM"),
                   calibration=cfg)
    with pytest.raises(InputError, match="not a PLUS orientation code"):
        read_sweep(write_mha(tmp_path / "x.mha", {"ProbeToTracker": probe_poses(), "ReferenceToTracker": reference_poses()}, orientation="MFX"),
                   calibration=cfg)
    with pytest.warns(SweepWarning, match="undefined"):
        read_sweep(write_mha(tmp_path / "u.mha", {"ProbeToTracker": probe_poses(), "ReferenceToTracker": reference_poses()}, orientation="??"),
                   calibration=cfg)


def test_calibration_files_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<PlusConfiguration><CoordinateDefinitions>")
    with pytest.raises(InputError, match="bad.xml: not a valid XML"):
        read_calibration(bad)
    empty = tmp_path / "empty.xml"
    empty.write_text("<PlusConfiguration/>")
    with pytest.raises(InputError, match="empty.xml: no CoordinateDefinitions"):
        read_calibration(empty)
    short = tmp_path / "m.txt"
    short.write_text("1 2 3")
    with pytest.raises(InputError, match="m.txt: expected 16 numbers"):
        read_calibration(short)
    sheared = write_config(tmp_path / "sheared.xml", sheared_calibration(shear_deg=9.0))
    mha = write_mha(tmp_path / "s.mha", {"ProbeToTracker": probe_poses(), "ReferenceToTracker": reference_poses()})
    with pytest.raises(InputError, match=r"sheared.xml: Transform Image→Probe.*sheared by 9.00°"):
        read_sweep(mha, calibration=sheared)
    cfg = read_calibration(write_config(tmp_path / "c.xml", sheared_calibration(),
                                        extra='<Transform From="Phantom" To="Reference" Matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1"/>',
                                        volume='ClipRectangleOrigin="167 62" ClipRectangleSize="495 488"'))
    assert set(cfg.transforms) == {("Image", "Probe"), ("Phantom", "Reference")}
    assert cfg.clip_origin_px == (167, 62) and cfg.clip_size_px == (495, 488)
    assert cfg.errors_mm[("Image", "Probe")] == 0.58


def test_plus_style_nrrd_with_a_2d_space(tmp_path):
    import nrrd

    cal, probe, ref = sheared_calibration(), probe_poses(), reference_poses()
    pixels = np.arange(N * H * W, dtype=np.uint8).reshape(N, H, W)
    header = {"kinds": ["domain", "domain", "list"], "space dimension": 2,
              "space directions": np.array([[1.0, 0.0], [0.0, 1.0], [np.nan, np.nan]]),
              "space origin": np.zeros(2), "ultrasound image orientation": "UFA", "encoding": "gzip"}
    for i in range(N):
        header[f"Seq_Frame{i:04d}_ProbeToTrackerTransform"] = format_matrix(probe[i])
        header[f"Seq_Frame{i:04d}_ReferenceToTrackerTransform"] = format_matrix(ref[i])
        header[f"Seq_Frame{i:04d}_Timestamp"] = str(5.0 + i)
    nrrd.write(str(tmp_path / "p.igs.nrrd"), np.transpose(pixels, (2, 1, 0)), header, index_order="F")
    s = read_sweep(tmp_path / "p.igs.nrrd", calibration=write_config(tmp_path / "c.xml", cal))
    np.testing.assert_array_equal(s.images, pixels[:, :, ::-1])     # UFA: columns flipped to MF
    np.testing.assert_allclose(s.timestamps, 5.0 + np.arange(N))
    np.testing.assert_allclose(world(s, 3, 2, 4), hand([np.linalg.inv(ref[3]), probe[3], cal], 2, 4), atol=1e-9)


def slicer_scene(tmp_path: Path, n=N, w=W, h=H):
    """An image sequence and two transform sequences laid out as 3D Slicer's Sequences module
    saves them (vtkMRMLVolumeSequenceStorageNode / vtkMRMLLinearTransformSequenceStorageNode):
    a 4-D .seq.nrrd in LPS with the index values on axis 3, and one .seq.mha per transform with
    DimSize 0 0 N, 'Transform =value' lines and a status and timestamp per frame."""
    import nrrd

    pixels = np.arange(n * h * w, dtype=np.uint8).reshape(n, h, w)
    sx, sy = 0.2, 0.3
    stamps = [f"{0.04 * i:.3f}" for i in range(n)]
    header = {"type": "unsigned char", "kinds": ["domain", "domain", "domain", "list"],
              "space": "left-posterior-superior",
              "space directions": np.array([[-sx, 0, 0], [0, -sy, 0], [0, 0, 1.0], [np.nan] * 3]),
              "space origin": np.array([4.0, -2.0, 0.5]), "labels": ["", "", "", "frame"],
              "encoding": "gzip", "DataNodeClassName": "vtkMRMLScalarVolumeNode",
              "axis 3 index type": "numeric", "axis 3 index values": " ".join(stamps)}
    vol = np.transpose(pixels, (2, 1, 0))[:, :, None, :]
    nrrd.write(str(tmp_path / "Image_Image-Seq.seq.nrrd"), vol, header, index_order="F")
    probe, ref = probe_poses(n), reference_poses(n)
    for name, mats in (("ProbeToTracker", probe), ("ReferenceToTracker", ref)):
        lines = ["ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
                 "CompressedData = False", f"DimSize = 0 0 {n}", "ElementSpacing = 1 1 1",
                 "Offset = 0 0 0", "TransformMatrix = 1 0 0 0 1 0 0 0 1", "ElementType = MET_UCHAR",
                 "Kinds = domain domain list"]
        for i in range(n):
            lines.append(f"Seq_Frame{i:04d}_{name}Transform =" + " ".join(f"{v:g}" if v == int(v) else repr(float(v))
                                                                          for v in mats[i].ravel()))
            lines.append(f"Seq_Frame{i:04d}_{name}TransformStatus = OK")
            lines.append(f"Seq_Frame{i:04d}_Timestamp = {stamps[i]}")
        lines.append("ElementDataFile = LOCAL")
        (tmp_path / f"{name}-Seq.seq.mha").write_text("\n".join(lines))
    d_lps = np.eye(4)
    d_lps[:3, :3] = np.diag([-sx, -sy, 1.0])
    d_lps[:3, 3] = [4.0, -2.0, 0.5]
    return pixels, probe, ref, d_lps


def test_slicer_sequences(tmp_path, capsys):
    """The frames are where Slicer shows them: transforms (RAS, written unchanged) · the volume's
    IJK → RAS (the NRRD's LPS geometry taken to RAS)."""
    pixels, probe, ref, d_lps = slicer_scene(tmp_path)
    ijk_to_ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ d_lps
    calib = rigid_from_euler([1, 2, 3], [0, 0, 90])          # Image (here: the volume's RAS) → Probe
    np.savetxt(tmp_path / "ImageToProbe.txt", calib)
    tr = [tmp_path / "ProbeToTracker-Seq.seq.mha", tmp_path / "ReferenceToTracker-Seq.seq.mha"]
    s = read_sweep(tmp_path / "Image_Image-Seq.seq.nrrd", transforms=tr, calibration=tmp_path / "ImageToProbe.txt")
    np.testing.assert_array_equal(s.images, pixels)
    np.testing.assert_allclose(s.timestamps, 0.04 * np.arange(N))
    np.testing.assert_allclose(s.spacing_mm, [[0.2, 0.3]] * N)
    for k in range(N):
        np.testing.assert_allclose(world(s, k, 3, 2),
                                   hand([np.linalg.inv(ref[k]), probe[k], calib, ijk_to_ras], 3, 2), atol=1e-9)
    with pytest.raises(InputError, match="no image data.*transform sequence"):
        read_sweep(tr[0])
    # the same from the command line
    out = tmp_path / "pts.npy"
    code = main(["sweep2points", str(tmp_path / "Image_Image-Seq.seq.nrrd"), "--transforms", str(tr[0]),
                 "--transforms", str(tr[1]), "--calibration", str(tmp_path / "ImageToProbe.txt"),
                 "--segment", "masks", "--masks", str(_masks(tmp_path)), "-o", str(out), "--quiet",
                 "--no-outliers"])
    assert code == 0, capsys.readouterr().err
    pts = np.load(out)
    np.testing.assert_allclose(pts[0], hand([np.linalg.inv(ref[0]), probe[0], calib, ijk_to_ras], 2, 3), atol=1e-9)


def _masks(tmp_path: Path) -> Path:
    m = np.zeros((N, H, W), dtype=bool)
    m[:, 3, 2:5] = True
    np.save(tmp_path / "masks.npy", m)
    return tmp_path / "masks.npy"


def test_sweep_options_on_the_command_line(tmp_path, capsys):
    cal, probe, ref = sheared_calibration(), probe_poses(), reference_poses()
    mha = write_mha(tmp_path / "s.igs.mha", {"ProbeToTracker": probe, "ReferenceToTracker": ref})
    cfg = write_config(tmp_path / "cfg.xml", cal)
    out = tmp_path / "pts.npz"
    args = ["sweep2points", str(mha), "--calibration", str(cfg), "--masks", str(_masks(tmp_path)),
            "-o", str(out), "--no-outliers"]
    assert main(args) == 0
    err = " ".join(capsys.readouterr().err.split())     # the log wraps long lines
    assert "pose chain Image→Reference = ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe" in err
    assert "(calibration cfg.xml)" in err
    data = np.load(out)
    i = int(np.flatnonzero(data["frame_index"] == 1)[0])
    c, r = data["pixel"][i]
    np.testing.assert_allclose(data["points"][i], hand([np.linalg.inv(ref[1]), probe[1], cal], c, r), atol=1e-9)
    # without the calibration: one line naming the file and what is missing, nothing written
    out.unlink()
    assert main(args[:2] + args[4:] + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "s.igs.mha" in err[0] and "--calibration" in err[0] and not out.exists()
    # sweep options for a point cloud are a usage error
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, np.random.default_rng(0).random((300, 3)))
    assert main(["reconstruct", str(cloud), "--calibration", str(cfg), "-o", str(tmp_path / "m.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--calibration applies to tracked sweeps" in err[0]


def test_warnings_are_one_line_each_and_dropped_on_failure(tmp_path, capsys):
    cal, probe = sheared_calibration(), probe_poses()
    mha = write_mha(tmp_path / "s.mha", {"ProbeToTracker": probe}, orientation=None)
    cfg = write_config(tmp_path / "cfg.xml", cal)
    out = tmp_path / "p.npy"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["sweep2points", str(mha), "--calibration", str(cfg), "--masks", str(_masks(tmp_path)),
                     "-o", str(out), "--quiet", "--no-outliers"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert any(line == f"ultraboneudf sweep2points: warning: {mha}: no UltrasoundImageOrientation; assuming MF"
               for line in err)
    assert any(line.startswith("ultraboneudf sweep2points: warning: ") and "Tracker (camera) frame" in line
               for line in err)
    assert all(line.startswith("ultraboneudf sweep2points: warning: ") for line in err)   # --quiet: no log
