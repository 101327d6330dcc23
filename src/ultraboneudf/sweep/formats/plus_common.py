"""What PLUS-style sequence readers (MetaIO ``.mha``/``.mhd`` and NRRD) share: the ultrasound image
orientation codes, and turning a resolved pose chain into the sweep's geometry.

Orientation (PLUS ``UltrasoundImageOrientation``): the first letter says where the image's +x
points (``M``: toward the marked side of the transducer, ``U``: the unmarked side), the second
where +y points (``F``: away from the transducer, ``N``: toward it); a third letter (``A``
ascending / ``D`` descending, the elevational axis) only matters for 3-D probes and reorders
nothing in a 2-D frame. PLUS calibrations are made for ``MF``, so frames are flipped to ``MF``.
RF-mode codes (``FM``, ``NM``, ``FU``, ``NU``: scan lines stored in rows) would need a transpose
and scan conversion: not supported.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..calibration import Calibration, read_calibration
from ..chain import PoseChain, frames_coplanar, split_transform_name
from ..model import Sweep, SweepWarning
from ..transforms import decompose_pixel_transform

B_MODE = ("MF", "MN", "UF", "UN")
RF_MODE = ("FM", "NM", "FU", "NU")
UNKNOWN = ("", "??", "XX")


def parse_orientation(code: str | None, path: Path, warn_missing: bool = True) -> tuple[bool, bool, str]:
    """``(flip columns, flip rows, normalised code)`` for an orientation code; ``None`` or an
    unknown-marker (``??``, ``XX``) is taken as ``MF`` with a warning (none for a missing code
    when ``warn_missing`` is false: 3D Slicer's volume sequences carry none and are shown as
    stored)."""
    raw = "" if code is None else str(code).strip().upper()
    if code is None and not warn_missing:
        return False, False, "MF"
    if raw in UNKNOWN:
        warnings.warn(f"{path}: {'no' if code is None else 'undefined (' + raw + ')'} "
                      f"UltrasoundImageOrientation; assuming MF", SweepWarning, stacklevel=3)
        return False, False, "MF"
    two, third = raw[:2], raw[2:]
    if two in RF_MODE:
        raise InputError(f"{path}: UltrasoundImageOrientation {raw} is an RF-mode layout (scan lines "
                         f"in rows); convert the frames to B-mode (MF) first")
    if two not in B_MODE or third not in ("", "A", "D"):
        raise InputError(f"{path}: UltrasoundImageOrientation {code!r} is not a PLUS orientation code "
                         f"(MF, MN, UF, UN, optionally followed by A or D)")
    return two[0] == "U", two[1] == "N", raw


def orient_to_mf(frames: np.ndarray, code: str | None, path: Path,
                 warn_missing: bool = True) -> tuple[np.ndarray, str]:
    """Frames ``(F, H, W)`` flipped from their stored orientation to ``MF``, and the code read."""
    flip_cols, flip_rows, norm = parse_orientation(code, path, warn_missing)
    if flip_cols:
        frames = frames[:, :, ::-1]
    if flip_rows:
        frames = frames[:, ::-1, :]
    return np.ascontiguousarray(frames), norm


def chain_geometry(chain: PoseChain, label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(kept frame indices (K,), rigid (K,4,4), spacing (K,2) mm, shear (K,) deg)`` of a chain's
    valid frames; a matrix that is not pixels → mm (sheared beyond tolerance, no spacing) raises
    :class:`InputError` naming ``label`` and the frame."""
    kept = np.flatnonzero(chain.ok)
    rigid, spacing, shear = [], [], []
    for i in kept:
        part = decompose_pixel_transform(chain.matrices[i], f"{label} (frame {i}, {chain.formula()})")
        rigid.append(part.rigid)
        spacing.append(part.spacing_mm)
        shear.append(part.shear_deg)
    return kept, np.stack(rigid), np.stack(spacing), np.asarray(shear)


def check_frames_spread(pixel_to_world: np.ndarray, image_size: tuple[int, int], path: Path,
                        chain: PoseChain | None = None) -> bool:
    """Reject frames that all share one pose (a fixed transform taken for tracking); warn, and
    return ``True``, when every frame lies in one plane (no 3-D extent)."""
    n = len(pixel_to_world)
    how = f" (chain {chain.formula()})" if chain is not None else ""
    if n >= 2 and np.abs(pixel_to_world - pixel_to_world[0]).max() <= 1e-9:
        raise InputError(f"{path}: all {n} frames have the same pose{how}: the transform is not "
                         f"tracking (a fixed offset or an untracked probe)")
    flat, thickness = frames_coplanar(pixel_to_world, image_size)
    if flat and n >= 2:
        warnings.warn(f"{path}: every frame lies in one plane{how} (extent across it "
                      f"{thickness:.2g} mm): no 3-D sweep", SweepWarning, stacklevel=3)
    return flat


def calibration_for(path: Path, calibration: Calibration | str | os.PathLike | None,
                    image_to_probe: np.ndarray | None, transform: str | None) -> Calibration | None:
    """The calibration of a chain: ``calibration`` (a :class:`Calibration` or a file), plus a bare
    ``image_to_probe`` matrix taken as ``Image → <From of transform>`` (``Probe`` by default), as
    is a matrix file."""
    probe = "Probe"
    pair = split_transform_name(transform) if transform else None
    if pair is not None and not pair[0].endswith("Image"):
        probe = pair[0]
    cal = calibration
    if cal is not None and not isinstance(cal, Calibration):
        cal = read_calibration(cal, to_frame=probe)
    if image_to_probe is not None:
        m = np.asarray(image_to_probe, dtype=np.float64)
        if m.shape != (4, 4):
            raise InputError(f"{path}: image_to_probe must be a 4×4 matrix, got shape {m.shape}")
        extra = {("Image", probe): m}
        cal = (Calibration(transforms=extra, source="image_to_probe") if cal is None else
               Calibration(**{**cal.__dict__, "transforms": {**cal.transforms, **extra}}))
    return cal


def clip_in_stored_pixels(calibration: Calibration | None, chain: PoseChain,
                          size: tuple[int, int]) -> list[int] | None:
    """The calibration's ultrasound region ``[column, row, width, height]`` in the stored pixels
    (shifted for a crop, clipped to the frame), or ``None``."""
    if calibration is None or not calibration.clip_origin_px or not calibration.clip_size_px:
        return None
    o = np.asarray(calibration.clip_origin_px, dtype=np.float64) - chain.crop_offset_px
    lo = np.clip(np.rint(o), 0, size).astype(int)
    hi = np.clip(np.rint(o + np.asarray(calibration.clip_size_px)), 0, size).astype(int)
    if not (hi > lo).all():
        return None
    return [int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])]


def sweep_from_chain(path: Path, pixels: np.ndarray, chain: PoseChain, orientation: str | None,
                     calibration: Calibration | None, as_masks: bool, layout: str,
                     timestamps: np.ndarray, meta: dict | None = None,
                     warn_missing_orientation: bool = True) -> Sweep:
    """The :class:`Sweep` of a PLUS-style sequence.

    Args:
        pixels: ``(F, H, W)`` frames as stored (flipped here to ``MF``).
        chain: the resolved pose chain (its valid frames are kept).
        orientation: the file's ``UltrasoundImageOrientation``.
        timestamps: ``(F,)`` of every stored frame.
        meta: extra entries for ``Sweep.meta``.
    """
    pixels, code = orient_to_mf(pixels, orientation, path, warn_missing_orientation)
    kept, rigid, spacing, shear = chain_geometry(chain, str(path))
    _, h, w = pixels.shape
    frames = pixels[kept]
    info = {"layout": layout, "transform": chain.formula(), "chain": chain.as_dict(),
            "chain_notes": list(chain.notes), "file_orientation": code, "frame_numbers": kept.tolist(),
            **(meta or {})}
    clip = clip_in_stored_pixels(calibration, chain, (w, h))
    if clip is not None:
        info["clip_rectangle_px"] = clip
    sweep = Sweep(image_to_world=rigid, spacing_mm=spacing, image_size=(w, h),
                  images=None if as_masks else frames, masks=frames != 0 if as_masks else None,
                  timestamps=np.asarray(timestamps, dtype=np.float64)[kept],
                  frame_names=[f"Seq_Frame{i:04d}" for i in kept], pixel_offset=0.0, orientation="MF",
                  source=str(path), meta=info, shear_deg=shear)
    info["coplanar"] = check_frames_spread(sweep.pixel_to_world(), sweep.image_size, path, chain)
    return sweep
