"""Bone segmentation: the classical detector on synthetic and real frames, and the learned-model
plug-in with tiny TorchScript/ONNX models built here."""

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from ultraboneudf.errors import InputError
from ultraboneudf.sweep import BoneDetector, LearnedSegmenter, segment_bone
from ultraboneudf.sweep.formats.images import read_image
from ultraboneudf.sweep.segment import rows_to_mask

SAMPLE = Path(__file__).resolve().parents[3] / "shared" / "data" / "ultrabones100k_sample"
SPACING = 0.1


def synthetic_frame(seed=0):
    """300×300 px at 0.1 mm: speckled tissue, a skin line (row 5), a fascia line with tissue below
    (row 60, columns 0-299), and a bone echo at row 150 + a gentle arc over columns 80-220 with an
    acoustic shadow below it."""
    rng = np.random.default_rng(seed)
    h = w = 300
    y = np.arange(h)[:, None]
    tissue = 0.35 * rng.rayleigh(1.0, (h, w)) / 1.25
    img = tissue.copy()
    img += 0.8 * np.exp(-0.5 * ((y - 5) / 1.5) ** 2)
    img += 0.6 * np.exp(-0.5 * ((y - 60) / 1.5) ** 2)
    cols = np.arange(w)
    bone_row = 150 + 0.002 * (cols - 150) ** 2
    bone = (cols >= 80) & (cols <= 220)
    shadow = np.where(bone[None, :] & (y > bone_row[None, :] + 3), 0.06, 1.0)
    img = img * shadow
    img += np.where(bone[None, :], 1.6 * np.exp(-0.5 * ((y - bone_row[None, :]) / 2.0) ** 2), 0.0)
    img = np.clip(255 * np.log1p(8 * img) / np.log1p(8 * 2.5), 0, 255).astype(np.uint8)
    return img, np.where(bone, bone_row, np.nan)


def test_classical_detector_finds_bone_not_fascia_or_skin():
    img, truth = synthetic_frame()
    rows = BoneDetector().surface_rows(img, SPACING)
    found = np.isfinite(rows)
    bone = np.isfinite(truth)
    assert found[bone].mean() > 0.9                        # the bone echo is found …
    assert np.abs(rows[bone & found] - truth[bone & found]).max() <= 3   # … within 0.3 mm
    assert not found[~bone][10:-10].any()                  # fascia (row 60) and skin (row 5) are not


def test_segment_mask_shape_and_thickness():
    img, truth = synthetic_frame(1)
    m = segment_bone(img, SPACING)
    assert m.shape == img.shape and m.dtype == bool
    assert m.sum(axis=0).max() == 1                         # one pixel per scan line
    m3 = segment_bone(img, SPACING, thickness_mm=0.2)
    assert m3.sum(axis=0).max() == 3


def test_detector_on_pure_speckle_finds_nothing():
    rng = np.random.default_rng(5)
    img = np.clip(80 * rng.rayleigh(1.0, (300, 300)), 0, 255).astype(np.uint8)
    assert not segment_bone(img, SPACING).any()


def test_detector_options_are_validated():
    with pytest.raises(InputError, match="unknown detector option"):
        BoneDetector.from_options({"nope": 1})


def test_rows_to_mask():
    m = rows_to_mask(np.array([np.nan, 2.4, 0.0]), 4, thickness_px=1)
    np.testing.assert_array_equal(np.argwhere(m), [[0, 2], [1, 2], [2, 1], [3, 1]])


@pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} not present")
def test_real_frame_bone_echo_found():
    # 190910.png: the fibula's echo arcs over columns ~580-880 at rows ~210-290 (looked at)
    rows = BoneDetector().surface_rows(read_image(SAMPLE / "frames" / "190910.png"), 0.05392)
    seg = rows[650:800]
    assert np.isfinite(seg).mean() > 0.9
    assert np.nanmin(seg) > 190 and np.nanmax(seg) < 300
    assert not np.isfinite(rows[:450]).any()   # tissue and fascia on the left: nothing


@pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} not present")
def test_real_frames_skin_line_never_detected():
    det = BoneDetector()
    files = sorted((SAMPLE / "frames").glob("*.png"))[::3] + sorted((SAMPLE / "examples").glob("*.png"))[::2]
    for f in files:
        rows = det.surface_rows(read_image(f), 0.05392)
        assert not (rows < 60).any(), f.name   # the skin line and probe face lie above row 60


# ---------------------------------------------------------------------------------------------
# learned models


class Threshold(torch.nn.Module):
    """Logit = 40·(x − 0.5): bone where the frame is brighter than mid-grey."""

    def __init__(self, channels: int = 1):
        super().__init__()
        self.conv = torch.nn.Conv2d(1, channels, 1)
        with torch.no_grad():
            if channels == 1:
                self.conv.weight.fill_(40.0)
                self.conv.bias.fill_(-20.0)
            else:  # two classes: background score 0, bone score 40·(x − 0.5)
                self.conv.weight.copy_(torch.tensor([0.0, 40.0]).view(2, 1, 1, 1))
                self.conv.bias.copy_(torch.tensor([0.0, -20.0]))

    def forward(self, x):
        return self.conv(x)


def _frame():
    img = np.zeros((40, 60), dtype=np.uint8)
    img[10:14, 5:50] = 220
    img[30, :] = 90
    return img


@pytest.mark.parametrize("channels", [1, 2])
def test_torchscript_model(tmp_path, channels):
    path = tmp_path / "model.pt"
    with warnings.catch_warnings():  # torch ≥ 2.10 deprecates TorchScript; users still have such files
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.script(Threshold(channels)), str(path))
    seg = LearnedSegmenter(path)
    assert seg.backend == "torchscript"
    img = _frame()
    np.testing.assert_array_equal(seg.segment(img), img > 127)
    prob = seg.predict(img)
    assert prob.shape == img.shape and 0 <= prob.min() and prob.max() <= 1


def test_torchscript_model_with_fixed_input_size(tmp_path):
    path = tmp_path / "model.ts"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.script(Threshold()), str(path))
    seg = LearnedSegmenter(path, input_size=(80, 120))
    m = seg.segment(_frame())
    assert m[11:13, 8:47].all() and not m[:8].any() and not m[16:].any()


def test_torch_export_program(tmp_path):
    path = tmp_path / "model.pt2"
    torch.export.save(torch.export.export(Threshold(), (torch.zeros(1, 1, 40, 60),)), str(path))
    seg = LearnedSegmenter(path)
    assert seg.backend == "torch.export" and seg.input_size == (40, 60)
    img = _frame()
    np.testing.assert_array_equal(seg.segment(img), img > 127)


def test_model_errors(tmp_path):
    with pytest.raises(InputError, match="no such model file"):
        LearnedSegmenter(tmp_path / "missing.pt")
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(b"not a model")
    with pytest.raises(InputError, match="garbage.pt: cannot load"):
        LearnedSegmenter(bad)
    (tmp_path / "m.h5").write_bytes(b"x")
    with pytest.raises(InputError, match="unknown model format"):
        LearnedSegmenter(tmp_path / "m.h5")


def test_model_with_wrong_output_shape(tmp_path):
    class Flat(torch.nn.Module):
        def forward(self, x):
            return x.flatten()

    path = tmp_path / "flat.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.script(Flat()), str(path))
    with pytest.raises(InputError, match="flat.pt: model output has shape"):
        LearnedSegmenter(path).segment(_frame())


def test_onnx_model(tmp_path):
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from onnx import TensorProto, helper, numpy_helper

    weight = numpy_helper.from_array(np.full((1, 1, 1, 1), 40.0, np.float32), "w")
    bias = numpy_helper.from_array(np.array([-20.0], np.float32), "b")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["x", "w", "b"], ["logit"]),
         helper.make_node("Sigmoid", ["logit"], ["prob"])],
        "threshold",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, 40, 60])],
        [helper.make_tensor_value_info("prob", TensorProto.FLOAT, [1, 1, 40, 60])],
        initializer=[weight, bias])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    path = tmp_path / "model.onnx"
    onnx.save(model, str(path))
    seg = LearnedSegmenter(path)
    assert seg.backend == "onnx" and seg.input_size == (40, 60)
    img = _frame()
    np.testing.assert_array_equal(seg.segment(img), img > 127)
    # a frame of another size is resized to the model's fixed input and back
    big = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
    assert seg.segment(big)[22:26, 12:96].all()
