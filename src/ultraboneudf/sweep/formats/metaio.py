"""PLUS sequence metafiles: MetaIO ``.mha`` (one file) and ``.mhd`` + ``.raw``/``.zraw``.

A small header parser, no ITK. The header is ``Key = Value`` lines up to ``ElementDataFile``;
per frame ``i`` PLUS writes ``Seq_Frame%04d_<From>To<To>Transform`` (16 numbers, row-major),
optionally ``…TransformStatus`` (``OK``/``INVALID``; INVALID frames are skipped, a missing status
means OK), ``…Timestamp``, ``…FrameNumber``, ``…ImageStatus``.

Geometry follows PLUS: the image frame is in *pixels* with the centre of the first pixel at the
origin (``pixel_offset = 0``); the pose chain to the reference (``ImageToReference`` directly, or
``ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe`` with the calibration from the PLUS
configuration, see :mod:`ultraboneudf.sweep.chain`) carries the mm-per-pixel scaling;
``ElementSpacing`` is not used for geometry. Frames stored in an orientation other than ``MF`` are
flipped to ``MF`` on reading (PLUS calibrations are for ``MF``; see
:mod:`ultraboneudf.sweep.formats.plus_common`).
"""

from __future__ import annotations

import os
import re
import warnings
import zlib
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...io import atomic_write_bytes
from ...io.inputs import check_input
from ..model import Sweep, SweepWarning
from ..transforms import format_matrix

SUFFIXES = (".mha", ".mhd")
MET_TYPES = {
    "MET_UCHAR": np.uint8, "MET_CHAR": np.int8, "MET_USHORT": np.uint16, "MET_SHORT": np.int16,
    "MET_UINT": np.uint32, "MET_INT": np.int32, "MET_ULONG_LONG": np.uint64,
    "MET_LONG_LONG": np.int64, "MET_FLOAT": np.float32, "MET_DOUBLE": np.float64,
}
_FRAME_KEY = re.compile(r"^Seq_Frame(\d+)_(.+)$")
MAX_HEADER_BYTES = 64 << 20
MAX_PIXEL_BYTES = int(os.environ.get("ULTRABONEUDF_MAX_PIXEL_BYTES", 16 << 30))
"""Largest pixel block a header may declare (bytes; environment ``ULTRABONEUDF_MAX_PIXEL_BYTES``):
a larger one is refused before anything is allocated or inflated."""


def detect(path: Path) -> bool:
    """A ``.mha`` or ``.mhd`` file (``.seq.mha`` included)."""
    return path.is_file() and path.suffix.lower() in SUFFIXES


def read_header(path: Path) -> tuple[dict[str, str], int]:
    """Parse the MetaIO text header: ``(fields, byte offset of the pixel data)``.

    Duplicated keys are tolerated with a warning (the last value wins). Raises
    :class:`InputError` naming the file when no ``ElementDataFile`` line ends the header.
    """
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    fields: dict[str, str] = {}
    pos = 0
    dup: list[str] = []
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        if not line:
            continue
        if "=" not in line:
            raise InputError(f"{path}: not a MetaIO header (line {line[:60]!r} has no '=')")
        key, value = (part.strip() for part in line.split("=", 1))
        if key in fields:
            dup.append(key)
        fields[key] = value
        if key == "ElementDataFile":
            if dup:
                warnings.warn(f"{path}: duplicated header key(s) {', '.join(sorted(set(dup))[:5])}; "
                              f"the last value is used", SweepWarning, stacklevel=3)
            return fields, pos
    raise InputError(f"{path}: not a MetaIO file (no ElementDataFile line ends the header)")


def _bool(value: str | None) -> bool:
    return str(value).strip().lower() in ("true", "1", "yes")


def _read_pixels(path: Path, fields: dict[str, str], data_offset: int,
                 shape: tuple[int, int, int], channels: int) -> np.ndarray:
    etype = fields.get("ElementType", "")
    if etype not in MET_TYPES:
        raise InputError(f"{path}: unsupported ElementType {etype!r}")
    dtype = np.dtype(MET_TYPES[etype])
    if _bool(fields.get("BinaryDataByteOrderMSB") or fields.get("ElementByteOrderMSB")):
        dtype = dtype.newbyteorder(">")
    target = fields["ElementDataFile"]
    if target == "LOCAL":
        data_path, offset = path, data_offset
    elif target.upper().startswith("LIST") or "%" in target:
        raise InputError(f"{path}: ElementDataFile = {target} (file lists) is not supported")
    else:
        data_path, offset = path.parent / target, int(fields.get("HeaderSize", 0) or 0)
        if Path(target).is_absolute() or not data_path.resolve().is_relative_to(path.parent.resolve()):
            raise InputError(f"{path}: ElementDataFile = {target} lies outside the header's folder; the "
                             f"pixel data must be beside it")
        check_input(data_path, "pixel data file")
    expected = int(np.prod(shape)) * channels * dtype.itemsize
    if expected > MAX_PIXEL_BYTES:
        raise InputError(f"{path}: the header declares {expected / 2**30:.1f} GiB of pixels ({shape[0]} "
                         f"frames of {shape[2]}x{shape[1]} px), above the limit of "
                         f"{MAX_PIXEL_BYTES / 2**30:.1f} GiB (set ULTRABONEUDF_MAX_PIXEL_BYTES to raise it)")
    try:
        with open(data_path, "rb") as fh:
            fh.seek(offset)
            blob = fh.read()
    except OSError as exc:
        raise InputError(f"{data_path}: cannot read the pixel data ({exc.strerror})") from None
    if _bool(fields.get("CompressedData")):
        try:
            # inflate no more than the header declares (+1 byte to see a surplus): a small file
            # cannot expand into gigabytes before it is found to be wrong
            blob = zlib.decompressobj().decompress(blob, expected + 1)
        except zlib.error as exc:
            raise InputError(f"{data_path}: corrupt compressed pixel data ({exc})") from None
    if len(blob) > expected:
        raise InputError(f"{data_path}: more pixel data than DimSize {shape[2]} {shape[1]} {shape[0]} "
                         f"declares (a wrong DimSize or ElementType?)")
    if len(blob) < expected:
        raise InputError(f"{data_path}: pixel data has {len(blob)} bytes, {expected} expected for "
                         f"{shape[0]} frames of {shape[2]}x{shape[1]} px (truncated file?)")
    arr = np.frombuffer(blob[:expected], dtype=dtype).reshape(*shape, channels)
    arr = arr.astype(dtype.newbyteorder("="), copy=False)
    if channels == 1:
        return arr[..., 0]
    grey = arr[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8) if arr.dtype == np.uint8 else grey


def frame_fields(fields: dict[str, str]) -> dict[int, dict[str, str]]:
    """``{frame number: {field name without the Seq_FrameNNNN_ prefix: value}}``."""
    out: dict[int, dict[str, str]] = {}
    for key, value in fields.items():
        m = _FRAME_KEY.match(key)
        if m:
            out.setdefault(int(m.group(1)), {})[m.group(2)] = value
    return out


def frame_timestamps(per_frame: dict[int, dict[str, str]], n: int) -> np.ndarray:
    """``Seq_FrameNNNN_Timestamp`` of every frame (the index where missing or malformed)."""
    out = np.arange(n, dtype=np.float64)
    for i in range(n):
        try:
            out[i] = float(per_frame.get(i, {}).get("Timestamp", i))
        except ValueError:
            pass
    return out


def read(path: str | os.PathLike, masks: str | os.PathLike | None = None,
         transform: str | None = None, image_to_probe: np.ndarray | None = None,
         as_masks: bool = False, calibration=None, reference: str | None = None,
         image_frame: str | None = None) -> Sweep:
    """Read a PLUS sequence metafile into a :class:`Sweep`.

    Args:
        path: ``.mha`` / ``.mhd`` (``.igs.mha``, ``.seq.mha``, …).
        masks: optional mask stack for the same frames (folder of PNGs, ``.npy``, ``.npz``).
        transform: a per-frame transform the pose chain must use (``ImageToReference``,
            ``ProbeToTracker``, …); by default the chain is resolved from what the file and the
            calibration hold (see :mod:`ultraboneudf.sweep.chain`).
        image_to_probe: 4×4 calibration (pixels → probe, with the scaling), as ``Image →`` the
            ``From`` frame of ``transform`` (``Probe`` by default).
        as_masks: the pixel data are bone masks (non-zero = bone), not B-mode frames.
        calibration: a PLUS device-set ``.xml``, a 4×4 matrix file, or a
            :class:`~ultraboneudf.sweep.calibration.Calibration`.
        reference: the output frame (default ``Reference``, else ``Tracker``).
        image_frame: the frame of the stored pixels (default ``Image``, or the crop frame).
    """
    from ..chain import FrameTransforms, resolve_chain
    from .images import load_mask_stack
    from .plus_common import calibration_for, sweep_from_chain

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    fields, data_offset = read_header(path)
    try:
        ndims = int(fields.get("NDims", "3"))
        dims = [int(v) for v in fields.get("DimSize", "").split()]
        channels = int(fields.get("ElementNumberOfChannels", "1"))
    except ValueError:
        raise InputError(f"{path}: malformed NDims/DimSize/ElementNumberOfChannels") from None
    if ndims not in (2, 3) or len(dims) != ndims or min(dims, default=0) < 0:
        raise InputError(f"{path}: expected NDims 3 (width height frames), got NDims {ndims}, "
                         f"DimSize {fields.get('DimSize')!r}")
    w, h = dims[0], dims[1]
    n = dims[2] if ndims == 3 else 1
    per_frame = frame_fields(fields)
    if w == 0 or h == 0 or n == 0:
        hint = (": a transform sequence (as 3D Slicer saves one); give it as the transforms of an "
                "image sequence (--transforms)" if per_frame else "")
        raise InputError(f"{path}: the sequence holds no image data (DimSize {fields.get('DimSize')}){hint}")
    cal = calibration_for(path, calibration, image_to_probe, transform)
    chain = resolve_chain(FrameTransforms(per_frame, n, path), cal, transform, reference, image_frame)
    pixels = _read_pixels(path, fields, data_offset, (n, h, w), channels)
    sweep = sweep_from_chain(path, pixels, chain, fields.get("UltrasoundImageOrientation"), cal,
                             as_masks, "metaio", frame_timestamps(per_frame, n))
    if np.allclose(sweep.spacing_mm, 1.0, atol=1e-9) and "ElementSpacing" in fields:
        es = fields["ElementSpacing"].split()[:2]
        if es and any(abs(float(v) - 1.0) > 1e-9 for v in es if _is_float(v)):
            warnings.warn(f"{path}: the {chain.formula()} transforms carry no scaling (1 mm/px); "
                          f"ElementSpacing {' '.join(es)} is ignored, as PLUS does", SweepWarning,
                          stacklevel=2)
    if masks is not None:
        sweep = sweep.with_masks(load_mask_stack(masks, sweep.n_frames, sweep.image_size))
    return sweep


def _is_float(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def write(sweep: Sweep, path: str | os.PathLike, compress: bool = False,
          transform: str = "ImageToReference", data: str = "images") -> Path:
    """Write ``sweep`` as a PLUS sequence metafile (``.mha``: one file; ``.mhd``: header plus
    ``.raw``/``.zraw``), atomically.

    The per-frame ``<transform>Transform`` is the sweep's pixel → world matrix with the PLUS pixel
    convention (centre of the first pixel at the origin), so reading back reproduces the geometry.
    ``data`` selects the pixel data: ``images`` or ``masks`` (written as 0/255 ``MET_UCHAR``).
    """
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"{path}: use a .mha or .mhd suffix")
    pixels = sweep.images if data == "images" else (
        None if sweep.masks is None else sweep.masks.astype(np.uint8) * 255)
    if pixels is None:
        raise ValueError(f"the sweep has no {data} to write")
    rev = {np.dtype(v): k for k, v in MET_TYPES.items()}
    dtype = pixels.dtype.newbyteorder("<") if pixels.dtype.itemsize > 1 else pixels.dtype
    etype = rev.get(np.dtype(pixels.dtype.newbyteorder("=")))
    if etype is None:
        raise ValueError(f"cannot write pixels of type {pixels.dtype}")
    blob = np.ascontiguousarray(pixels, dtype=dtype).tobytes()
    if compress:
        blob = zlib.compress(blob, 6)
    n = sweep.n_frames
    mats = sweep.pixel_to_world()  # PLUS: pixel index (c, r) is the pixel centre, as here
    suffix = ".zraw" if compress else ".raw"
    data_name = "LOCAL" if path.suffix.lower() == ".mha" else path.with_suffix(suffix).name
    lines = [
        "ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
        "BinaryDataByteOrderMSB = False", "CenterOfRotation = 0 0 0",
        f"CompressedData = {'True' if compress else 'False'}",
    ]
    if compress:
        lines.append(f"CompressedDataSize = {len(blob)}")
    lines += [
        f"DimSize = {sweep.width} {sweep.height} {n}", "ElementNumberOfChannels = 1",
        "ElementSpacing = 1 1 1", "Offset = 0 0 0", "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "Kinds = domain domain list", "UltrasoundImageOrientation = MF",
        "UltrasoundImageType = BRIGHTNESS",
    ]
    for i in range(n):
        p = f"Seq_Frame{i:04d}_"
        lines += [f"{p}FrameNumber = {i}", f"{p}{transform}Transform = {format_matrix(mats[i])}",
                  f"{p}{transform}TransformStatus = OK",
                  f"{p}Timestamp = {repr(float(sweep.timestamps[i]))}", f"{p}ImageStatus = OK"]
    lines += [f"ElementType = {etype}", f"ElementDataFile = {data_name}"]
    header = ("\n".join(lines) + "\n").encode("latin-1")
    if data_name == "LOCAL":
        atomic_write_bytes(path, header + blob)
    else:
        atomic_write_bytes(path.with_suffix(suffix), blob)
        atomic_write_bytes(path, header)
    return path
