"""PNG frames and mask stacks (Pillow), with errors that name the file."""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, UnidentifiedImageError

from ...errors import InputError
from ...io import atomic_write_bytes
from ...io.inputs import check_fits_memory
from ...progress import QUIET, Progress

IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg")


MAX_FRAME_PIXELS = 64_000_000
"""A frame declaring more pixels than this (8000 × 8000) is refused before it is decoded: an
ultrasound frame is a few hundred thousand, a decompression bomb billions."""


def read_image(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read one frame as a 2-D array ``(H, W)``: 8-bit grey (colour is converted to grey),
    16-bit grey kept as ``uint16``. Raises :class:`InputError` naming the file if it is not a
    regular file, unreadable, or declares in its header another size than ``size`` ``(W, H)`` or
    more than :data:`MAX_FRAME_PIXELS` pixels (checked before the pixels are decoded)."""
    path = Path(path)
    if path.exists() and not path.is_file():
        raise InputError(f"{path}: not a regular file (a folder, a named pipe or a device)")
    try:
        with Image.open(path) as im:
            w, h = im.size
            if size is not None and (w, h) != tuple(size):
                raise InputError(f"{path}: image is {w}x{h} px, expected {size[0]}x{size[1]} (the first "
                                 f"frame's size, or image_size_px of the calibration)")
            if w * h > MAX_FRAME_PIXELS:
                raise InputError(f"{path}: the image declares {w}x{h} px, more than "
                                 f"{MAX_FRAME_PIXELS:,} pixels; not an ultrasound frame (a decompression bomb?)")
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L"):
                return np.asarray(im, dtype=np.uint16)
            if im.mode in ("I", "F"):
                return np.asarray(im)
            if im.mode != "L":
                im = im.convert("L")
            return np.asarray(im, dtype=np.uint8)
    except FileNotFoundError:
        raise InputError(f"{path}: missing image file") from None
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(f"{path}: unreadable image ({type(exc).__name__}: {exc})") from None


def png_bytes(array: np.ndarray) -> bytes:
    """Encode a 2-D ``uint8`` (or bool: 0/255) array as PNG bytes."""
    arr = np.asarray(array)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    if arr.dtype != np.uint16:
        arr = arr.astype(np.uint8, copy=False)
    im = Image.fromarray(np.ascontiguousarray(arr))
    buf = io.BytesIO()
    im.save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def write_png(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write a 2-D array as a PNG atomically (bool masks as 0/255)."""
    atomic_write_bytes(path, png_bytes(array))


def read_stack(paths: Sequence[Path], size: tuple[int, int] | None = None,
               progress: Progress = QUIET) -> np.ndarray:
    """Read frames into ``(F, H, W)``; every frame must have the same size (and ``size`` =
    ``(W, H)`` if given), else :class:`InputError` naming the first differing file."""
    with progress.stage("read frames", len(paths)) as advance:
        return _read_stack(paths, size, advance)


def _read_stack(paths: Sequence[Path], size: tuple[int, int] | None, advance) -> np.ndarray:
    frames = []
    for p in paths:
        arr = read_image(p, size)  # a frame of another size is refused before it is decoded
        if size is None:
            size = (arr.shape[1], arr.shape[0])
            check_fits_memory(p, 2 * len(paths) * arr.nbytes, f"{len(paths)} frames of {size[0]}x{size[1]} px")
        frames.append(arr)
        advance()
    if not frames:
        return np.zeros((0, 0, 0), dtype=np.uint8)
    return np.stack(frames)


def load_mask_stack(path: str | os.PathLike, n_frames: int, size: tuple[int, int] | None,
                    frame_names: Sequence[str] | None = None) -> np.ndarray:
    """Bone masks for a sweep: a folder of images or a NumPy file (``.npy``; ``.npz`` array ``masks``).

    Args:
        path: folder of mask images (matched to ``frame_names`` by file stem when all are
            present, else taken in sorted order) or an array file of shape ``(F, H, W)``.
        n_frames: ``F``, the number of frames of the sweep.
        size: ``(W, H)`` of the frames, or ``None`` to take it from the masks.
        frame_names: stems of the sweep's frame files, for matching.

    Returns:
        ``(F, H, W)`` bool, True where bone (any non-zero value).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such mask file or folder")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        by_stem = {p.stem: p for p in files}
        if frame_names and all(Path(n).stem in by_stem for n in frame_names):
            chosen = [by_stem[Path(n).stem] for n in frame_names]
        elif len(files) != n_frames:
            raise InputError(f"{path}: {len(files)} mask images for {n_frames} frames")
        else:
            chosen = files
        masks = read_stack(chosen, size)
    else:
        try:
            if path.suffix.lower() == ".npz":
                with np.load(path, allow_pickle=False) as data:
                    if "masks" not in data:
                        raise InputError(f"{path}: no array named 'masks' (found: {', '.join(data.files)})")
                    masks = data["masks"]
            elif path.suffix.lower() == ".npy":
                masks = np.load(path, allow_pickle=False)
            else:
                raise InputError(f"{path}: masks must be a folder of images, .npy or .npz")
        except (ValueError, OSError) as exc:
            raise InputError(f"{path}: cannot read masks ({exc})") from None
    masks = np.asarray(masks)
    if masks.ndim == 2 and n_frames == 1:
        masks = masks[None]
    if size is None and masks.ndim == 3:
        size = (masks.shape[2], masks.shape[1])
    if size is None:
        raise InputError(f"{path}: masks must be a (frames, height, width) array, got {masks.shape}")
    if masks.shape != (n_frames, size[1], size[0]):
        raise InputError(f"{path}: masks have shape {masks.shape}, expected "
                         f"({n_frames}, {size[1]}, {size[0]}) = (frames, height, width)")
    return masks != 0
