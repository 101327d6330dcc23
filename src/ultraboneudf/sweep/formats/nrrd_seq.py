"""3D Slicer image sequences as NRRD (``.seq.nrrd``), read and written with pynrrd.

The list (frame) axis is the last (``kinds: domain domain domain list``, current Slicer) or the
first (``kinds: list domain domain domain``, older files); both are accepted, as is a plain
``domain domain list``. Each frame is a 2-D image (one domain axis of size 1 is dropped).

Geometry: ``pixel → world = T_i · D`` where ``D`` is the frame's index → image-node map from
``space directions`` / ``space origin`` (or ``spacings``), with the first pixel's centre at the
origin (``pixel_offset = 0``), and ``T_i`` the pose chain (see :mod:`ultraboneudf.sweep.chain`)
of the per-frame transforms, read from ``Seq_FrameNNNN_<Name>Transform`` key/value fields
(PLUS-style, 16 numbers row-major) or from companion transform sequences given as
``transforms=`` (3D Slicer saves each transform sequence as its own ``.seq.mha``), and the
calibration.

Frames: a PLUS ``.igs.nrrd`` has ``space dimension: 2`` (the image plane, in pixels, no
anatomical space): ``D`` is used as is. A 3D Slicer ``.seq.nrrd`` names an anatomical ``space``
(``left-posterior-superior``, as ITK writes) while Slicer's transforms act in RAS: ``D`` is taken
to RAS first, which is where Slicer shows the frames. The transforms themselves are never
converted (Slicer writes them unchanged), so the points come out in the transforms' frame.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...io import atomic_write_bytes
from ..model import Sweep
from ..transforms import format_matrix
from . import metaio


def detect(path: Path) -> bool:
    """A ``.nrrd`` / ``.nhdr`` file (``.seq.nrrd`` included)."""
    return path.is_file() and path.suffix.lower() in (".nrrd", ".nhdr")


def _import_nrrd():
    try:
        import nrrd  # noqa: PLC0415  (lazy: only NRRD users pay for it)
    except ImportError:  # pragma: no cover - pynrrd is a core dependency
        raise InputError("reading .nrrd needs pynrrd: pip install pynrrd") from None
    return nrrd


SPACE_TO_RAS = {"right-anterior-superior": (1, 1, 1), "ras": (1, 1, 1),
                "left-anterior-superior": (-1, 1, 1), "las": (-1, 1, 1),
                "left-posterior-superior": (-1, -1, 1), "lps": (-1, -1, 1)}
"""Axis signs that take a NRRD's anatomical ``space`` to RAS, 3D Slicer's world."""


def _index_to_image(header: dict, domain_axes: list[int], path: Path) -> tuple[np.ndarray, bool]:
    """4×4 ``D`` (pixel index → image-node mm; RAS when the header names an anatomical space) and
    whether the header gave any spacing. A 2-D space (``space dimension: 2``, as PLUS writes) is
    the image plane itself."""
    d = np.eye(4)
    if "space directions" in header:
        sd = np.asarray(header["space directions"], dtype=np.float64)
        dim = sd.shape[1] if sd.ndim == 2 else 3
        vecs = [np.pad(sd[a], (0, 3 - dim)) if dim < 3 else sd[a][:3] for a in domain_axes]
        if any(not np.isfinite(v).all() for v in vecs):
            raise InputError(f"{path}: 'space directions' is 'none' for an image axis")
        if len(vecs) == 2:
            n = np.cross(vecs[0], vecs[1])
            vecs.append(n / max(np.linalg.norm(n), 1e-12))
        for k in range(3):
            d[:3, k] = vecs[k]
        origin = header.get("space origin")
        if origin is not None:
            o = np.asarray(origin, dtype=np.float64).reshape(-1)[:3]
            d[:len(o), 3] = o
        signs = SPACE_TO_RAS.get(str(header.get("space", "")).strip().lower())
        if signs is not None:
            d = np.diag([*signs, 1.0]) @ d
        return d, True
    if "spacings" in header:
        sp = np.asarray(header["spacings"], dtype=np.float64)
        for k, a in enumerate(domain_axes[:3]):
            if np.isfinite(sp[a]):
                d[k, k] = sp[a]
        return d, True
    return d, False


def _field(header: dict, name: str) -> str | None:
    """A key/value field by name, ignoring case and spaces (``ultrasound image orientation``,
    ``UltrasoundImageOrientation``)."""
    want = name.replace(" ", "").lower()
    for k, v in header.items():
        if isinstance(v, str) and k.replace(" ", "").lower() == want:
            return v
    return None


def _companion_fields(transforms) -> tuple[dict[int, dict[str, str]], str]:
    """Per-frame fields merged from one or more transform sequence files (3D Slicer writes one
    ``.seq.mha`` per transform), matched to the images by frame index."""
    files = [transforms] if isinstance(transforms, (str, os.PathLike)) else list(transforms)
    merged: dict[int, dict[str, str]] = {}
    names = []
    for t in files:
        tpath = Path(t)
        if not tpath.is_file():
            raise InputError(f"{tpath}: no such transform file")
        fields, _ = metaio.read_header(tpath)
        for i, f in metaio.frame_fields(fields).items():
            merged.setdefault(i, {}).update(f)
        names.append(str(tpath))
    return merged, " + ".join(names)


_NRRD_TYPE_BYTES = {t: n for n, names in {
    1: ("signed char", "int8", "int8_t", "uchar", "unsigned char", "uint8", "uint8_t"),
    2: ("short", "short int", "signed short", "signed short int", "int16", "int16_t", "ushort",
        "unsigned short", "unsigned short int", "uint16", "uint16_t"),
    4: ("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t", "float"),
}.items() for t in names}


def _check_declared_size(path: Path, header: dict) -> None:
    """Refuse, before pynrrd allocates or inflates anything, a header declaring more pixel bytes than
    :data:`~.metaio.MAX_PIXEL_BYTES` (types not listed count 8 bytes a sample)."""
    sizes = [int(v) for v in np.atleast_1d(header.get("sizes", []))]
    declared = int(np.prod(sizes, dtype=np.float64)) * _NRRD_TYPE_BYTES.get(str(header.get("type", "")), 8)
    if declared > metaio.MAX_PIXEL_BYTES:
        raise InputError(f"{path}: the header declares {declared / 2**30:.1f} GiB of samples (sizes "
                         f"{' '.join(map(str, sizes))}), above the limit of {metaio.MAX_PIXEL_BYTES / 2**30:.1f} GiB "
                         f"(set ULTRABONEUDF_MAX_PIXEL_BYTES to raise it)")


def read(path: str | os.PathLike, masks: str | os.PathLike | None = None,
         transform: str | None = None, transforms=None, as_masks: bool = False,
         calibration=None, reference: str | None = None, image_frame: str | None = None,
         image_to_probe: np.ndarray | None = None) -> Sweep:
    """Read a NRRD image sequence (3D Slicer ``.seq.nrrd``, PLUS ``.igs.nrrd``) into a
    :class:`Sweep`.

    Args:
        path: the NRRD file.
        masks: optional mask stack for the same frames (folder of PNGs, ``.npy``, ``.npz``).
        transform, calibration, reference, image_frame, image_to_probe: the pose chain, as for
            :func:`ultraboneudf.sweep.formats.metaio.read`.
        transforms: transform sequence file(s) (``.seq.mha`` as 3D Slicer writes them, or any
            PLUS metafile) holding the per-frame transforms, when the NRRD has none.
        as_masks: the pixel data are bone masks (non-zero = bone), not B-mode frames.
    """
    from ..chain import FrameTransforms, resolve_chain
    from .images import load_mask_stack
    from .plus_common import calibration_for, sweep_from_chain

    nrrd = _import_nrrd()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        _check_declared_size(path, nrrd.read_header(str(path)))
        data, header = nrrd.read(str(path), index_order="F")
    except InputError:
        raise
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError, zlib errors
        raise InputError(f"{path}: cannot read NRRD ({type(exc).__name__}: {exc})") from None
    ndim = data.ndim
    kinds = [str(k).lower() for k in header.get("kinds", [])]
    if kinds and len(kinds) == ndim:
        list_axes = [i for i, k in enumerate(kinds) if k in ("list", "time", "point")]
    else:
        list_axes = [ndim - 1] if ndim in (3, 4) else []
    if len(list_axes) != 1 or ndim not in (3, 4):
        single = " (a single image, not a sequence)" if ndim == 2 else ""
        raise InputError(f"{path}: expected a sequence of 2-D frames (kinds 'domain domain list', "
                         f"'domain domain domain list' or 'list domain domain domain'), got dimension "
                         f"{ndim}, kinds {' '.join(kinds) or 'unset'}{single}")
    la = list_axes[0]
    domain_axes = [i for i in range(ndim) if i != la]
    frames = np.moveaxis(data, la, 0)  # (F, X, Y[, Z])
    if len(domain_axes) == 3:
        if frames.shape[3] == 1:
            frames = frames[..., 0]
        elif frames.shape[1] == 1:  # frames stored as Y-Z slices: not an ultrasound image layout
            raise InputError(f"{path}: frames are not 2-D in the x-y plane (sizes {list(data.shape)})")
        else:
            raise InputError(f"{path}: each frame is a 3-D volume (sizes {list(data.shape)}); "
                             f"expected 2-D frames")
    frames = np.ascontiguousarray(np.transpose(frames, (0, 2, 1)))  # (F, H, W)
    n, h, w = frames.shape
    d, has_spacing = _index_to_image(header, domain_axes, path)

    per_frame = metaio.frame_fields({k: str(v) for k, v in header.items() if isinstance(v, str)})
    tsource: str | Path = path
    if transforms is not None:
        per_frame, tsource = _companion_fields(transforms)
    elif not any(k.endswith("Transform") for f in per_frame.values() for k in f):
        raise InputError(f"{path}: no per-frame transforms (Seq_FrameNNNN_…Transform fields), so "
                         f"the frames have no pose; give the transform sequence (--transforms FILE)")
    cal = calibration_for(path, calibration, image_to_probe, transform)
    chain = resolve_chain(FrameTransforms(per_frame, n, tsource), cal, transform, reference, image_frame)
    chain.matrices = chain.matrices @ d
    axes = np.linalg.norm(chain.matrices[chain.ok][:, :3, :2], axis=1)
    if not has_spacing and np.allclose(axes, 1.0, atol=1e-9):
        raise InputError(f"{path}: no pixel spacing (no 'space directions' or 'spacings', and the "
                         f"{chain.formula()} transforms carry no scaling)")
    stamps = metaio.frame_timestamps(per_frame, n)
    if not any("Timestamp" in f for f in per_frame.values()):
        values = str(header.get(f"axis {la} index values", "")).split()
        if len(values) == n:
            try:
                stamps = np.asarray([float(v) for v in values])
            except ValueError:
                pass
    sweep = sweep_from_chain(path, frames, chain, _field(header, "UltrasoundImageOrientation"), cal,
                             as_masks, "nrrd", stamps,
                             {"space": header.get("space"), "list_axis": la},
                             warn_missing_orientation=False)
    if masks is not None:
        sweep = sweep.with_masks(load_mask_stack(masks, sweep.n_frames, sweep.image_size))
    return sweep


def write(sweep: Sweep, path: str | os.PathLike, list_axis: str = "last",
          transform: str = "ImageToReference", data: str = "images",
          space: str = "left-posterior-superior") -> Path:
    """Write ``sweep`` as a Slicer-style ``.seq.nrrd`` (gzip), atomically.

    ``space directions`` carry the first frame's pixel spacing (in ``space``, LPS by default, as
    Slicer writes volumes); per-frame ``Seq_FrameNNNN_<transform>Transform`` fields carry the pose
    in the sweep's own frame, so that ``T_i · D_RAS`` (how Slicer places a volume under a
    transform, and how :func:`read` reads it back) reproduces the sweep's pixel → world map.
    ``list_axis`` is ``last`` (current Slicer) or ``first`` (older files).
    """
    nrrd = _import_nrrd()
    path = Path(path)
    pixels = sweep.images if data == "images" else (
        None if sweep.masks is None else sweep.masks.astype(np.uint8) * 255)
    if pixels is None:
        raise ValueError(f"the sweep has no {data} to write")
    n = sweep.n_frames
    sx, sy = sweep.spacing_mm[0]
    signs = SPACE_TO_RAS.get(space.lower(), (1, 1, 1))
    d_inv = np.linalg.inv(np.diag([*signs, 1.0]) @ np.diag([sx, sy, 1.0, 1.0]))
    mats = sweep.pixel_to_world()
    vol = np.transpose(pixels, (0, 2, 1))[..., None]  # (F, W, H, 1)
    dirs = np.array([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]])
    if list_axis == "last":
        vol = np.moveaxis(vol, 0, 3)
        kinds = ["domain", "domain", "domain", "list"]
        sd = np.vstack([dirs, np.full((1, 3), np.nan)])
        la = 3
    elif list_axis == "first":
        kinds = ["list", "domain", "domain", "domain"]
        sd = np.vstack([np.full((1, 3), np.nan), dirs])
        la = 0
    else:
        raise ValueError("list_axis must be 'last' or 'first'")
    header: dict = {"kinds": kinds, "space": space, "space directions": sd,
                    "space origin": np.zeros(3), "encoding": "gzip",
                    "UltrasoundImageOrientation": "MF",
                    f"axis {la} index type": "numeric",
                    f"axis {la} index values": " ".join(repr(float(t)) for t in sweep.timestamps)}
    for i in range(n):
        header[f"Seq_Frame{i:04d}_{transform}Transform"] = format_matrix(mats[i] @ d_inv)
        header[f"Seq_Frame{i:04d}_Timestamp"] = repr(float(sweep.timestamps[i]))
    buf = io.BytesIO()
    nrrd.write(buf, vol, header, index_order="F")
    atomic_write_bytes(path, buf.getvalue())
    return path

