"""Every real PLUS file in ../shared/data/plus (PlusLibData, third-party): read with its calibration,
frame count, spacing and one pixel's world position against a hand computation from the header
and the configuration; the bone and spine sweeps reconstruct end to end; the others fail with one
line and exit 2."""

import json
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.io import sidecar_path
from ultraboneudf.errors import InputError
from ultraboneudf.sweep import SweepWarning, read_sweep

PLUS = Path(__file__).resolve().parents[3] / "shared" / "data" / "plus"
pytestmark = pytest.mark.skipif(not PLUS.is_dir(), reason=f"{PLUS} not present")

BONE, BONE_CFG = "BoneUltrasound_L14.igs.mha", "BoneUltrasound_L14_config.xml"
SPINE, SPINE_CFG = "SpinePhantomFreehand.igs.mha", "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml"
NWIRE_CFG = "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"


def header_field(name: str, key: str) -> str:
    """One header value, read straight from the file's text (no project code)."""
    raw = (PLUS / name).read_bytes()
    end = raw.index(b"\n\n") if name.endswith(".nrrd") else raw.index(b"ElementDataFile")
    head = raw[:end].decode("latin-1")
    sep = ":=" if name.endswith(".nrrd") else "="
    m = re.search(rf"^{re.escape(key)}\s*{re.escape(sep)}\s*(.*?)\s*$", head, flags=re.M)
    assert m, key
    return m.group(1)


def matrix(text: str) -> np.ndarray:
    return np.array(text.split(), dtype=float).reshape(4, 4)


def image_to_probe(config: str) -> np.ndarray:
    root = ET.parse(PLUS / config).getroot()
    t = next(t for t in root.iter("Transform") if (t.get("From"), t.get("To")) == ("Image", "Probe"))
    return matrix(t.get("Matrix"))


def hand_world(name: str, config: str, frame: int, c: float, r: float, crop=(0.0, 0.0)) -> np.ndarray:
    """PLUS: ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe · [c, r, 0, 1] (pixels of the
    MF image; a crop's pixel is shifted by its offset first)."""
    p = matrix(header_field(name, f"Seq_Frame{frame:04d}_ProbeToTrackerTransform"))
    ref = matrix(header_field(name, f"Seq_Frame{frame:04d}_ReferenceToTrackerTransform"))
    return (np.linalg.inv(ref) @ p @ image_to_probe(config) @ [c + crop[0], r + crop[1], 0, 1])[:3]


def raw_frames(name: str) -> np.ndarray:
    """The stored pixels of a compressed MetaIO file, decoded by hand: (frames, rows, columns)."""
    raw = (PLUS / name).read_bytes()
    start = raw.index(b"ElementDataFile = LOCAL") + len(b"ElementDataFile = LOCAL")
    start = raw.index(b"\n", start) + 1
    w, h, n = (int(v) for v in header_field(name, "DimSize").split())
    return np.frombuffer(zlib.decompress(raw[start:]), np.uint8).reshape(n, h, w)


@pytest.mark.parametrize("name, config, frames, size, spacing, shear", [
    (BONE, BONE_CFG, 21, (820, 616), (0.085435, 0.085435), 0.0),
    (SPINE, SPINE_CFG, 21, (820, 616), (0.085421, 0.079004), -2.745),
    ("NwirePhantomFreehand.igs.mha", NWIRE_CFG, 97, (820, 616), (0.078104, 0.074359), 0.905),
    ("NwirePhantomFreehand.igs.nrrd", NWIRE_CFG, 97, (820, 616), (0.078104, 0.074359), 0.905),
])
def test_tracked_file_geometry_matches_hand_computation(name, config, frames, size, spacing, shear):
    s = read_sweep(PLUS / name, calibration=PLUS / config)
    assert s.n_frames == frames and s.image_size == size
    cal = image_to_probe(config)
    # the calibration's column norms (the tracking matrices, rounded to 6 digits, move them 1e-6)
    np.testing.assert_allclose(s.spacing_mm[0], np.linalg.norm(cal[:3, :2], axis=0), rtol=1e-5)
    np.testing.assert_allclose(s.spacing_mm[0], spacing, atol=2e-6)
    assert s.shear_deg[0] == pytest.approx(shear, abs=2e-3)
    assert s.meta["chain"]["chain"] == "ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe"
    k, (c, r) = 7, (413, 288)
    got = (s.pixel_to_world()[k] @ [c, r, 0, 1])[:3]
    np.testing.assert_allclose(got, hand_world(name, config, k, c, r), atol=1e-6)


def test_orientation_mfa_is_used_as_stored_and_mf_too():
    for name, config in ((SPINE, SPINE_CFG), (BONE, BONE_CFG)):
        s = read_sweep(PLUS / name, calibration=PLUS / config)
        np.testing.assert_array_equal(s.images[3], raw_frames(name)[3])
        assert s.meta["file_orientation"] == header_field(name, "UltrasoundImageOrientation")


def test_nrrd_and_metafile_of_the_same_sequence_agree():
    a = read_sweep(PLUS / "NwirePhantomFreehand.igs.mha", calibration=PLUS / NWIRE_CFG)
    b = read_sweep(PLUS / "NwirePhantomFreehand.igs.nrrd", calibration=PLUS / NWIRE_CFG)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_allclose(a.pixel_to_world(), b.pixel_to_world(), atol=1e-9)
    np.testing.assert_allclose(a.timestamps, b.timestamps)


def test_cropped_sequence_maps_back_through_its_offset():
    crop = read_sweep(PLUS / "NwirePhantomFreehandCropped.igs.mha", calibration=PLUS / NWIRE_CFG)
    full = read_sweep(PLUS / "NwirePhantomFreehand.igs.mha", calibration=PLUS / NWIRE_CFG)
    assert crop.n_frames == 20 and crop.image_size == (200, 150)
    off = -matrix(header_field("NwirePhantomFreehandCropped.igs.mha",
                               "Seq_Frame0000_ImageToCroppedImageTransform"))[:2, 3]   # (335, 285)
    np.testing.assert_allclose(off, [335, 285])
    k = int(np.flatnonzero(full.timestamps == crop.timestamps[4])[0])
    c, r = 120, 80
    np.testing.assert_array_equal(crop.images[4], full.images[k, 285:435, 335:535])
    np.testing.assert_allclose((crop.pixel_to_world()[4] @ [c, r, 0, 1])[:3],
                               (full.pixel_to_world()[k] @ [c + 335, r + 285, 0, 1])[:3], atol=1e-9)
    np.testing.assert_allclose((crop.pixel_to_world()[4] @ [c, r, 0, 1])[:3],
                               hand_world("NwirePhantomFreehandCropped.igs.mha", NWIRE_CFG, 4, c, r, off),
                               atol=1e-6)
    # the frames spread in 3-D (the offset is not taken as the pose)
    corners = crop.pixel_to_world()[:, :3, 3]
    assert np.ptp(corners, axis=0).max() > 5


def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ultraboneudf.cli", *map(str, args)],
                          capture_output=True, text=True)


@pytest.mark.parametrize("name, config, words", [
    ("NrrdSample.igs.nrrd", None, "a single image, not a sequence"),
    ("Prostate10_video.igs.mhd", None, "calibration Image→Tool"),
    ("NwirePhantomFreehandCropped.igs.mha", None, "ImageToProbe is missing"),
    (BONE, None, "no calibration"),
    ("NwirePhantomFreehand.igs.mha", NWIRE_CFG, "no bone found in any of the 97 frames"),
    ("NwirePhantomFreehandCropped.igs.mha", NWIRE_CFG, "no frame images soft tissue"),
])
def test_files_that_cannot_give_bone_fail_with_one_line(tmp_path, name, config, words):
    out = tmp_path / "pts.ply"
    extra = ["--calibration", PLUS / config] if config else []
    res = run_cli("sweep2points", PLUS / name, *extra, "-o", out, "--quiet")
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert name in lines[0] and words in lines[0] and "Traceback" not in res.stderr
    assert not out.exists()


def test_prostate_with_a_calibration_names_the_missing_frame(tmp_path):
    np.savetxt(tmp_path / "cal.txt", np.diag([0.3, 0.3, 0.3, 1.0]))
    with pytest.warns(SweepWarning, match="duplicated header key"), \
            pytest.raises(InputError, match=r"10 frames \(DimSize\) but 9 ToolToTrackerTransform fields "
                                            r"\(no transform for frame 2\)"):
        read_sweep(PLUS / "Prostate10_video.igs.mhd", calibration=tmp_path / "cal.txt",
                   transform="ToolToTracker")


@pytest.mark.parametrize("name, config", [(BONE, BONE_CFG), (SPINE, SPINE_CFG)])
def test_bone_and_spine_reconstruct_end_to_end(tmp_path, capsys, name, config):
    out = tmp_path / "mesh.ply"
    code = main(["reconstruct", str(PLUS / name), "--calibration", str(PLUS / config), "--preset", "fast",
                 "--iters", "300", "--set", "extract.max_depth=6", "-o", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    side = json.loads(sidecar_path(out).read_text())
    sweep = side["input"]["sweep"]
    assert side["counts"]["faces"] > 500
    assert sweep["pose_chain"]["chain"] == "ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe"
    assert sweep["pose_chain"]["reference_frame"] == "Reference"
    assert sweep["points"]["count"] == side["counts"]["input_points"] > 1000
    assert side["counts"]["frames"] == sweep["points"]["frames_with_bone"] == 21  # the frames went along
    assert sweep["outlier_removal"] == {"rule": "local", "k": 16, "factor": 1.5}
    assert sweep["fragments"]["groups"] >= 1 and sweep["fragments"]["removed"] >= 0
    assert sweep["shear_deg"] == pytest.approx(-2.745 if name == SPINE else 0.0, abs=2e-3)
    import trimesh

    mesh = trimesh.load(out, process=False)
    assert len(mesh.faces) == side["counts"]["faces"]


def test_reconstructing_the_cloud_sweep2points_wrote_equals_reconstructing_the_sweep(tmp_path, capsys):
    """The PLY that ``sweep2points`` writes carries each point's probe position and frame, and
    ``reconstruct`` takes them up: the robust preset's planes face the probe and bridge the gaps
    between frames exactly as for the sweep itself, so the two meshes are the same."""
    import trimesh

    cloud = tmp_path / "bone.ply"
    assert main(["sweep2points", str(PLUS / BONE), "--calibration", str(PLUS / BONE_CFG), "-o", str(cloud),
                 "--quiet"]) == 0
    run = ["--iters", "300", "--set", "extract.max_depth=6", "--quiet"]
    assert main(["reconstruct", str(PLUS / BONE), "--calibration", str(PLUS / BONE_CFG),
                 "-o", str(tmp_path / "from_sweep.ply"), *run]) == 0
    assert main(["reconstruct", str(cloud), "-o", str(tmp_path / "from_cloud.ply"), *run]) == 0
    a = trimesh.load(tmp_path / "from_sweep.ply", process=False)
    b = trimesh.load(tmp_path / "from_cloud.ply", process=False)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-5)
    side = json.loads(sidecar_path(tmp_path / "from_cloud.ply").read_text())
    assert side["input"]["sweep_columns"] == ["probe", "frame"] and side["counts"]["frames"] == 21
    # the x, y, z alone (a cloud from another tool) carry neither
    xyz = tmp_path / "bone.xyz"
    np.savetxt(xyz, trimesh.load(cloud, process=False).vertices)
    assert main(["reconstruct", str(xyz), "-o", str(tmp_path / "from_xyz.ply"), *run]) == 0
    side = json.loads(sidecar_path(tmp_path / "from_xyz.ply").read_text())
    assert "sweep_columns" not in side["input"] and side["counts"]["frames"] == 0
