"""Plug-in for a learned bone-segmentation model loaded from the user's own file.

No weights are downloaded or shipped: the user points at a TorchScript file (``.pt``, ``.pth``,
``.ts``, ``.torchscript``, ``.jit``; saved with ``torch.jit.save``), a ``torch.export`` program
(``.pt2``; saved with ``torch.export.save``; its example input fixes the input size) or an ONNX file
(``.onnx``, needs the optional ``onnxruntime``: ``pip install 'ultraboneudf[onnx]'``).

Model contract (what the file must compute):

* input: one float32 tensor ``(1, 1, H, W)``, the B-mode frame scaled to [0, 1] (grey / 255 for
  8-bit frames; ``normalize='zscore'`` gives zero mean, unit variance instead). Frames are resized
  (bilinear) to ``input_size`` when given, or to the fixed size an ONNX model declares.
* output: ``(1, 1, h, w)`` / ``(1, h, w)`` / ``(h, w)`` bone probability or logit, or
  ``(1, 2, h, w)`` two-class scores (channel 1 = bone, softmax). ``output='auto'`` applies a
  sigmoid when any value lies outside [0, 1]. The map is resized back to the frame and compared
  with ``threshold``.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError

TORCHSCRIPT_SUFFIXES = (".pt", ".pth", ".ts", ".torchscript", ".jit")
EXPORT_SUFFIXES = (".pt2",)
ONNX_SUFFIXES = (".onnx",)


def _import_onnxruntime(path: Path):
    try:
        import onnxruntime  # noqa: PLC0415  (optional extra, imported only when used)
    except ImportError:
        raise InputError(f"{path}: ONNX models need onnxruntime, which is not installed; "
                         f"install it with: pip install 'ultraboneudf[onnx]' (or pip install "
                         f"onnxruntime), or export the model to TorchScript") from None
    return onnxruntime


def _resize(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of a 2-D float array to ``size = (H, W)`` (half-pixel centres)."""
    import torch  # noqa: PLC0415

    if arr.shape == tuple(size):
        return arr
    t = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))[None, None]
    out = torch.nn.functional.interpolate(t, size=tuple(int(v) for v in size), mode="bilinear",
                                          align_corners=False)
    return out[0, 0].numpy()


class LearnedSegmenter:
    """A bone segmenter backed by a TorchScript or ONNX model file (see the module docstring).

    Args:
        path: the model file.
        threshold: probability above which a pixel is bone.
        device: ``cpu`` or ``cuda`` (TorchScript only; ONNX runs on onnxruntime's default provider).
        input_size: ``(H, W)`` the model expects, or ``None`` to feed frames at their own size.
        normalize: ``unit`` (grey / max of the dtype) or ``zscore`` (per frame).
        output: ``auto``, ``logits`` or ``probability``.

    Raises:
        InputError: naming the file when it is missing, has an unknown suffix, cannot be loaded, or
        (on first use) produces an output of the wrong shape.
    """

    def __init__(self, path: str | os.PathLike, threshold: float = 0.5, device: str = "cpu",
                 input_size: tuple[int, int] | None = None, normalize: str = "unit",
                 output: str = "auto") -> None:
        self.path = Path(path)
        self.threshold = float(threshold)
        self.device = device
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        if normalize not in ("unit", "zscore"):
            raise InputError(f"normalize must be 'unit' or 'zscore', got {normalize!r}")
        if output not in ("auto", "logits", "probability"):
            raise InputError(f"output must be 'auto', 'logits' or 'probability', got {output!r}")
        self.normalize = normalize
        self.output = output
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such model file")
        suffix = self.path.suffix.lower()
        if suffix in TORCHSCRIPT_SUFFIXES:
            self._run = self._load_torchscript()
            self.backend = "torchscript"
        elif suffix in EXPORT_SUFFIXES:
            self._run = self._load_exported()
            self.backend = "torch.export"
        elif suffix in ONNX_SUFFIXES:
            self._run = self._load_onnx()
            self.backend = "onnx"
        else:
            raise InputError(f"{self.path}: unknown model format {suffix!r}; use TorchScript "
                             f"({', '.join(TORCHSCRIPT_SUFFIXES)}), torch.export (.pt2) or ONNX (.onnx)")

    # ----------------------------------------------------------------------------------------

    def _load_torchscript(self) -> Callable[[np.ndarray], np.ndarray]:
        import torch  # noqa: PLC0415

        try:
            with warnings.catch_warnings():  # torch ≥ 2.10 deprecates TorchScript; it still loads
                warnings.simplefilter("ignore", DeprecationWarning)
                module = torch.jit.load(str(self.path), map_location=self.device)
        except Exception as exc:  # RuntimeError for non-TorchScript files, pickle errors, …
            raise InputError(f"{self.path}: cannot load as a TorchScript model "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
                             ) from None
        module.eval()

        def run(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                out = module(torch.from_numpy(x).to(self.device))
            if isinstance(out, (tuple, list)):
                out = out[0]
            if isinstance(out, dict):
                out = next(iter(out.values()))
            return out.detach().float().cpu().numpy()

        return run

    def _load_exported(self) -> Callable[[np.ndarray], np.ndarray]:
        import torch  # noqa: PLC0415

        try:
            program = torch.export.load(str(self.path))
        except Exception as exc:
            raise InputError(f"{self.path}: cannot load as a torch.export program "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
                             ) from None
        example = getattr(program, "example_inputs", None)
        if self.input_size is None and example and example[0]:
            shape = tuple(example[0][0].shape)
            if len(shape) == 4:
                self.input_size = (int(shape[2]), int(shape[3]))
        module = program.module()

        def run(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                out = module(torch.from_numpy(x))
            if isinstance(out, (tuple, list)):
                out = out[0]
            return out.detach().float().cpu().numpy()

        return run

    def _load_onnx(self) -> Callable[[np.ndarray], np.ndarray]:
        ort = _import_onnxruntime(self.path)
        try:
            session = ort.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise InputError(f"{self.path}: cannot load as an ONNX model ({type(exc).__name__}: "
                             f"{exc})") from None
        inp = session.get_inputs()[0]
        shape = inp.shape
        if self.input_size is None and len(shape) == 4 and all(isinstance(v, int) for v in shape[2:]):
            self.input_size = (int(shape[2]), int(shape[3]))
        name = inp.name

        def run(x: np.ndarray) -> np.ndarray:
            return np.asarray(session.run(None, {name: x})[0], dtype=np.float32)

        return run

    # ----------------------------------------------------------------------------------------

    def _prepare(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim != 2:
            raise ValueError(f"expected a 2-D frame, got shape {img.shape}")
        x = img.astype(np.float32)
        if self.normalize == "unit":
            scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
            x = x / scale
        else:
            x = (x - x.mean()) / max(float(x.std()), 1e-6)
        if self.input_size is not None:
            x = _resize(x, self.input_size)
        return np.ascontiguousarray(x[None, None], dtype=np.float32)

    def predict(self, image: np.ndarray) -> np.ndarray:
        """Bone probability ``(H, W)`` float32 in [0, 1] for one frame ``(H, W)``."""
        x = self._prepare(image)
        try:
            out = self._run(x)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"{self.path}: the model failed on a {x.shape} input "
                             f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
                             ) from None
        out = np.asarray(out, dtype=np.float32)
        while out.ndim > 3 and out.shape[0] == 1:
            out = out[0]
        if out.ndim == 2:
            out = out[None]
        if out.ndim != 3 or out.shape[0] not in (1, 2):
            raise InputError(f"{self.path}: model output has shape {np.shape(out)}; expected "
                             f"(1, 1, h, w), (1, h, w), (h, w) or (1, 2, h, w)")
        if out.shape[0] == 2:
            e = np.exp(out - out.max(axis=0, keepdims=True))
            prob = e[1] / e.sum(axis=0)
        else:
            prob = out[0]
            if self.output == "logits" or (self.output == "auto" and (prob.min() < 0.0 or prob.max() > 1.0)):
                prob = 1.0 / (1.0 + np.exp(-np.clip(prob, -60, 60)))
        h, w = np.asarray(image).shape
        return np.clip(_resize(prob, (h, w)), 0.0, 1.0)

    def segment(self, image: np.ndarray, spacing_mm: Any = None) -> np.ndarray:
        """Bone mask ``(H, W)`` bool of one frame (``spacing_mm`` is accepted and unused)."""
        return self.predict(image) >= self.threshold

    def segment_stack(self, images: np.ndarray, spacing_mm: Any = None,
                      advance: Callable[[int], None] | None = None) -> np.ndarray:
        """Masks ``(F, H, W)`` bool for frames ``(F, H, W)``."""
        images = np.asarray(images)
        out = np.zeros(images.shape, dtype=bool)
        for i in range(len(images)):
            out[i] = self.segment(images[i])
            if advance is not None:
                advance(1)
        return out


def load_model(path: str | os.PathLike, **options: Any) -> LearnedSegmenter:
    """Load a user's TorchScript/ONNX bone-segmentation model (see :class:`LearnedSegmenter`)."""
    return LearnedSegmenter(path, **options)


def is_model_path(text: str) -> bool:
    """True if ``text`` names a file with a model suffix (TorchScript or ONNX)."""
    return Path(text).suffix.lower() in TORCHSCRIPT_SUFFIXES + EXPORT_SUFFIXES + ONNX_SUFFIXES
