"""3D Slicer image sequences as NRRD (``.seq.nrrd``), read and written with pynrrd.

The list (frame) axis is the last (``kinds: domain domain domain list``, current Slicer) or the
first (``kinds: list domain domain domain``, older files); both are accepted, as is a plain
``domain domain list``. Each frame is a 2-D image (one domain axis of size 1 is dropped).

Geometry: ``pixel → world = T_i · D`` where ``D`` is the frame's index → image-node map from
``space directions`` / ``space origin`` (or ``spacings``), with the first pixel's centre at the
origin (``pixel_offset = 0``), and ``T_i`` the per-frame transform, read from
``Seq_FrameNNNN_<Name>Transform`` key/value fields (PLUS-style, 16 numbers row-major) or from a
companion PLUS metafile given as ``transforms=``. Nothing is converted between LPS and RAS: the
points come out in the transforms' frame, as Slicer does for sequence transforms.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...io import atomic_write_bytes
from ..model import Sweep
from ..transforms import format_matrix, split_scaled_transform
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


def _index_to_image(header: dict, domain_axes: list[int], path: Path) -> tuple[np.ndarray, bool]:
    """4×4 ``D`` (pixel index → image-node mm) and whether the header gave any spacing."""
    d = np.eye(4)
    if "space directions" in header:
        sd = np.asarray(header["space directions"], dtype=np.float64)
        vecs = [sd[a] for a in domain_axes]
        if any(not np.isfinite(v).all() for v in vecs):
            raise InputError(f"{path}: 'space directions' is 'none' for an image axis")
        if len(vecs) == 2:
            n = np.cross(vecs[0], vecs[1])
            vecs.append(n / max(np.linalg.norm(n), 1e-12))
        for k in range(3):
            d[:3, k] = vecs[k][:3]
        origin = header.get("space origin")
        if origin is not None:
            d[:3, 3] = np.asarray(origin, dtype=np.float64)[:3]
        return d, True
    if "spacings" in header:
        sp = np.asarray(header["spacings"], dtype=np.float64)
        for k, a in enumerate(domain_axes[:3]):
            if np.isfinite(sp[a]):
                d[k, k] = sp[a]
        return d, True
    return d, False


def read(path: str | os.PathLike, masks: str | os.PathLike | None = None,
         transform: str | None = None, transforms: str | os.PathLike | None = None,
         as_masks: bool = False) -> Sweep:
    """Read a Slicer ``.seq.nrrd`` image sequence into a :class:`Sweep`.

    Args:
        path: the NRRD file.
        masks: optional mask stack for the same frames (folder of PNGs, ``.npy``, ``.npz``).
        transform: per-frame transform name (``ImageToReference`` by default).
        transforms: a PLUS metafile holding the per-frame transforms, when the NRRD has none.
        as_masks: the pixel data are bone masks (non-zero = bone), not B-mode frames.
    """
    from .images import load_mask_stack

    nrrd = _import_nrrd()
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        data, header = nrrd.read(str(path), index_order="F")
    except Exception as exc:  # pynrrd raises NRRDError, ValueError, OSError, zlib errors
        raise InputError(f"{path}: cannot read NRRD ({type(exc).__name__}: {exc})") from None
    ndim = data.ndim
    kinds = [str(k).lower() for k in header.get("kinds", [])]
    if kinds and len(kinds) == ndim:
        list_axes = [i for i, k in enumerate(kinds) if k in ("list", "time", "point")]
    else:
        list_axes = [ndim - 1] if ndim in (3, 4) else []
    if len(list_axes) != 1 or ndim not in (3, 4):
        raise InputError(f"{path}: expected a sequence of 2-D frames (kinds 'domain domain domain "
                         f"list' or 'list domain domain domain'), got dimension {ndim}, kinds "
                         f"{' '.join(kinds) or 'unset'}")
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

    source_fields = {k: str(v) for k, v in header.items() if isinstance(v, str)}
    tpath = path
    if transforms is not None:
        tpath = Path(transforms)
        if not tpath.is_file():
            raise InputError(f"{tpath}: no such transform file")
        source_fields, _ = metaio.read_header(tpath)
    elif not metaio.frame_fields(source_fields):
        raise InputError(f"{path}: no per-frame transforms (Seq_FrameNNNN_…Transform fields), so "
                         f"the frames have no pose; give the transform sequence (transforms=…)")
    mats, kept, stamps, labels, name = metaio.read_frame_transforms(tpath, source_fields, n, transform)
    if "Timestamp" not in next(iter(metaio.frame_fields(source_fields).values()), {}):
        values = str(header.get(f"axis {la} index values", "")).split()
        if len(values) == n:
            try:
                stamps = np.asarray([float(values[i]) for i in kept])
            except ValueError:
                pass
    rigid, spacing = [], []
    for m, label in zip(mats, labels):
        r, s = split_scaled_transform(m @ d, f"{tpath}: {label}_{name}Transform")
        rigid.append(r)
        spacing.append(s)
    spacing_arr = np.asarray(spacing)
    if not has_spacing and np.allclose(spacing_arr, 1.0, atol=1e-9):
        raise InputError(f"{path}: no pixel spacing (no 'space directions' or 'spacings', and the "
                         f"{name} transforms carry no scaling)")
    frames = frames[kept]
    images, mask_arr = (None, frames != 0) if as_masks else (frames, None)
    sweep = Sweep(image_to_world=np.stack(rigid), spacing_mm=spacing_arr, image_size=(w, h),
                  images=images, masks=mask_arr, timestamps=stamps, frame_names=labels,
                  pixel_offset=0.0, orientation="MF", source=str(path),
                  meta={"layout": "nrrd", "transform": name, "space": header.get("space"),
                        "list_axis": la})
    if masks is not None:
        sweep = sweep.with_masks(load_mask_stack(masks, sweep.n_frames, sweep.image_size))
    return sweep


def write(sweep: Sweep, path: str | os.PathLike, list_axis: str = "last",
          transform: str = "ImageToReference", data: str = "images",
          space: str = "left-posterior-superior") -> Path:
    """Write ``sweep`` as a Slicer-style ``.seq.nrrd`` (gzip), atomically.

    ``space directions`` carry the first frame's pixel spacing; per-frame
    ``Seq_FrameNNNN_<transform>Transform`` fields carry the pose, so ``T_i · D`` reproduces the
    sweep's pixel → world map. ``list_axis`` is ``last`` (current Slicer) or ``first`` (older
    files). ``space`` is only a label: transforms are written unchanged (no LPS/RAS conversion).
    """
    nrrd = _import_nrrd()
    path = Path(path)
    pixels = sweep.images if data == "images" else (
        None if sweep.masks is None else sweep.masks.astype(np.uint8) * 255)
    if pixels is None:
        raise ValueError(f"the sweep has no {data} to write")
    n = sweep.n_frames
    sx, sy = sweep.spacing_mm[0]
    d_inv = np.diag([1.0 / sx, 1.0 / sy, 1.0, 1.0])
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
                    f"axis {la} index type": "numeric",
                    f"axis {la} index values": " ".join(repr(float(t)) for t in sweep.timestamps)}
    for i in range(n):
        header[f"Seq_Frame{i:04d}_{transform}Transform"] = format_matrix(mats[i] @ d_inv)
        header[f"Seq_Frame{i:04d}_Timestamp"] = repr(float(sweep.timestamps[i]))
    buf = io.BytesIO()
    nrrd.write(buf, vol, header, index_order="F")
    atomic_write_bytes(path, buf.getvalue())
    return path

