"""Bad sweeps give one clear InputError naming the file, and the CLI exits with 2 and writes nothing."""

import shutil
from pathlib import Path

import numpy as np
import pytest

from ultraboneudf.cli import main
from ultraboneudf.errors import InputError
from ultraboneudf.sweep import Sweep, read_sweep
from ultraboneudf.sweep.formats import metaio, ultrabones
from ultraboneudf.sweep.transforms import format_matrix, rigid_from_euler


def good_folder(tmp_path: Path) -> Path:
    rng = np.random.default_rng(3)
    n, w, h = 4, 10, 8
    poses = np.stack([rigid_from_euler([i, 2 * i, 3], [0, 10 * i, 0]) for i in range(n)])
    images = rng.integers(0, 255, (n, h, w), dtype=np.uint8)
    s = Sweep(image_to_world=poses, spacing_mm=0.2, image_size=(w, h), images=images,
              timestamps=np.arange(n) * 10.0 + 100)
    return ultrabones.write(s, tmp_path / "sweep")


def run_cli(args, capsys):
    code = main(args)
    err = capsys.readouterr().err
    return code, err


def expect_error(path: Path, named: str, words: str, capsys, tmp_path):
    with pytest.raises(InputError, match=words) as info:
        read_sweep(path)
    assert named in str(info.value)
    out = tmp_path / "out.ply"
    code, err = run_cli(["sweep2points", str(path), "-o", str(out), "--quiet"], capsys)
    assert code == 2
    assert named in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_missing_frame(tmp_path, capsys):
    root = good_folder(tmp_path)
    (root / "frames" / "110.png").unlink()
    # the pose row still lists it, and frames/ now has fewer files than poses
    expect_error(root, "110.png", "missing frame", capsys, tmp_path)


def test_pose_count_differs_from_frame_count(tmp_path, capsys):
    root = good_folder(tmp_path)
    shutil.copy(root / "frames" / "100.png", root / "frames" / "999.png")
    expect_error(root, "poses.csv", "4 poses but", capsys, tmp_path)


def test_non_rigid_calibration(tmp_path, capsys):
    root = good_folder(tmp_path)
    cal = root / "calibration.json"
    text = cal.read_text()
    import json

    data = json.loads(text)
    data.pop("translation_mm")
    data.pop("euler_xyz_deg")
    data["matrix"] = np.diag([1.0, 1.0, 2.0, 1.0]).tolist()
    cal.write_text(json.dumps(data))
    expect_error(root, "calibration.json", "not rigid", capsys, tmp_path)


def test_no_pixel_spacing(tmp_path, capsys):
    root = good_folder(tmp_path)
    lines = (root / "poses.csv").read_text().splitlines()
    header = lines[0].split(",")
    k = header.index("space_factor")
    drop = [",".join(c for j, c in enumerate(line.split(",")) if j != k) for line in lines]
    (root / "poses.csv").write_text("\n".join(drop) + "\n")
    import json

    data = json.loads((root / "calibration.json").read_text())
    data.pop("pixel_spacing_mm")
    (root / "calibration.json").write_text(json.dumps(data))
    expect_error(root, "poses.csv", "no pixel spacing", capsys, tmp_path)


def test_unreadable_image(tmp_path, capsys):
    root = good_folder(tmp_path)
    (root / "frames" / "120.png").write_bytes(b"this is not a PNG")
    expect_error(root, "120.png", "unreadable image", capsys, tmp_path)


def test_malformed_pose_row(tmp_path, capsys):
    root = good_folder(tmp_path)
    text = (root / "poses.csv").read_text().replace("110,0.2,", "110,0.2,abc,", 1)
    (root / "poses.csv").write_text(text)
    expect_error(root, "poses.csv: line 3", "cannot parse", capsys, tmp_path)


def test_missing_calibration(tmp_path, capsys):
    root = good_folder(tmp_path)
    (root / "calibration.json").unlink()
    expect_error(root, "calibration.json", "missing calibration", capsys, tmp_path)


def _mha(path: Path, transforms: list[np.ndarray], frames: int, w=4, h=3):
    lines = [f"Seq_Frame{i:04d}_ImageToReferenceTransform = {format_matrix(m)}"
             for i, m in enumerate(transforms)]
    head = (f"ObjectType = Image\nNDims = 3\nDimSize = {w} {h} {frames}\nElementType = MET_UCHAR\n"
            "UltrasoundImageOrientation = MF\n" + "\n".join(lines) + "\nElementDataFile = LOCAL\n")
    path.write_bytes(head.encode() + bytes(w * h * frames))
    return path


def test_metaio_transform_count_differs(tmp_path, capsys):
    p = _mha(tmp_path / "a.mha", [np.diag([0.1, 0.1, 1, 1])] * 2, frames=3)
    expect_error(p, "a.mha", "3 frames .* but 2", capsys, tmp_path)


def test_metaio_sheared_transform(tmp_path, capsys):
    m = np.diag([0.1, 0.1, 1.0, 1.0])
    m[0, 1] = 0.05
    p = _mha(tmp_path / "b.mha", [m], frames=1)
    expect_error(p, "Seq_Frame0000", "not rigid", capsys, tmp_path)


def test_metaio_no_pixel_spacing(tmp_path, capsys):
    p = _mha(tmp_path / "c.mha", [np.diag([0.0, 0.1, 1.0, 1.0])], frames=1)
    expect_error(p, "c.mha", "no pixel spacing", capsys, tmp_path)


def test_metaio_truncated_pixels(tmp_path, capsys):
    p = _mha(tmp_path / "d.mha", [np.diag([0.1, 0.1, 1.0, 1.0])] * 2, frames=2)
    p.write_bytes(p.read_bytes()[:-5])
    expect_error(p, "d.mha", "truncated", capsys, tmp_path)


def test_nrrd_without_spacing_or_transforms(tmp_path, capsys):
    import nrrd

    vol = np.zeros((4, 3, 1, 2), dtype=np.uint8)
    nrrd.write(str(tmp_path / "x.seq.nrrd"), vol, {"kinds": ["domain", "domain", "domain", "list"]})
    expect_error(tmp_path / "x.seq.nrrd", "x.seq.nrrd", "no per-frame transforms", capsys, tmp_path)
    hdr = {"kinds": ["domain", "domain", "domain", "list"],
           "Seq_Frame0000_ImageToReferenceTransform": format_matrix(np.eye(4)),
           "Seq_Frame0001_ImageToReferenceTransform": format_matrix(np.eye(4))}
    nrrd.write(str(tmp_path / "y.seq.nrrd"), vol, hdr)
    expect_error(tmp_path / "y.seq.nrrd", "y.seq.nrrd", "no pixel spacing", capsys, tmp_path)


def test_missing_sweep_path(tmp_path, capsys):
    expect_error(tmp_path / "nowhere", "nowhere", "no such file", capsys, tmp_path)


def test_metaio_write_then_corrupt_compressed(tmp_path, capsys):
    s = Sweep(image_to_world=[np.eye(4)], spacing_mm=0.1, image_size=(4, 3),
              images=np.zeros((1, 3, 4), np.uint8))
    p = metaio.write(s, tmp_path / "z.mhd", compress=True)
    p.with_suffix(".zraw").write_bytes(b"garbage")
    expect_error(p, "z.zraw", "corrupt compressed", capsys, tmp_path)


def test_metaio_pixel_block_beyond_the_limit_is_refused_before_reading(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(metaio, "MAX_PIXEL_BYTES", 100)
    p = _mha(tmp_path / "e.mha", [np.diag([0.1, 0.1, 1.0, 1.0])] * 3, frames=3, w=8, h=5)   # 120 bytes
    expect_error(p, "e.mha", "declares .* GiB of pixels .* ULTRABONEUDF_MAX_PIXEL_BYTES", capsys, tmp_path)


def test_metaio_zlib_bomb_is_not_inflated_beyond_the_header(tmp_path, capsys):
    """1 MB of zeros compresses to ~1 kB; a header that declares 24 bytes gets an error, and the
    reader never holds more than 25 inflated bytes."""
    import zlib

    p = _mha(tmp_path / "z.mha", [np.diag([0.1, 0.1, 1.0, 1.0])] * 2, frames=2)
    head = p.read_bytes()[:-24].replace(b"ElementDataFile", b"CompressedData = True\nElementDataFile")
    p.write_bytes(head + zlib.compress(bytes(1 << 20)))
    expect_error(p, "z.mha", "more pixel data than DimSize", capsys, tmp_path)


def test_metaio_more_pixels_than_dimsize_is_an_error(tmp_path, capsys):
    p = _mha(tmp_path / "f.mha", [np.diag([0.1, 0.1, 1.0, 1.0])] * 2, frames=2)
    p.write_bytes(p.read_bytes() + bytes(12))    # half a frame more than DimSize says
    expect_error(p, "f.mha", "more pixel data than DimSize", capsys, tmp_path)


def test_nrrd_samples_beyond_the_limit_are_refused_before_reading(tmp_path, capsys, monkeypatch):
    import nrrd

    vol = np.zeros((8, 5, 1, 3), dtype=np.uint16)                    # 240 bytes
    nrrd.write(str(tmp_path / "big.seq.nrrd"), vol, {"kinds": ["domain", "domain", "domain", "list"],
                                                      "encoding": "gzip"})
    monkeypatch.setattr(metaio, "MAX_PIXEL_BYTES", 200)
    expect_error(tmp_path / "big.seq.nrrd", "big.seq.nrrd", "declares .* GiB of samples .* ULTRABONEUDF_MAX_PIXEL_BYTES",
                 capsys, tmp_path)
    monkeypatch.setattr(metaio, "MAX_PIXEL_BYTES", 240)              # at the limit: read, then its own errors
    expect_error(tmp_path / "big.seq.nrrd", "big.seq.nrrd", "no per-frame transforms", capsys, tmp_path)
