"""Sweep file formats, one module per layout (readers, and writers where the layout has one), and a
registry that detects the layout of a path.

| layout | what | module |
| --- | --- | --- |
| ``ultrabones`` | folder: ``poses.csv``, ``calibration.json``, ``frames/*.png`` (+ ``masks/``) | :mod:`.ultrabones` |
| ``metaio`` | PLUS sequence metafile ``.mha`` / ``.mhd`` (+ ``.raw``/``.zraw``) | :mod:`.metaio` |
| ``nrrd`` | 3D Slicer ``.seq.nrrd`` image sequence, PLUS ``.igs.nrrd`` | :mod:`.nrrd_seq` |

Masks for any layout can be given separately (``masks=``: a folder of PNGs, ``.npy`` or ``.npz``),
matched to the frames by file stem or by order.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path
from typing import Any, Callable, NamedTuple

from ...errors import InputError
from ...progress import QUIET, Progress
from ..model import Sweep
from . import metaio, nrrd_seq, ultrabones


class Layout(NamedTuple):
    """A registered sweep layout: ``detect(path) -> bool``, ``read(path, **options) -> Sweep``,
    ``write(sweep, path, **options)``."""

    name: str
    detect: Callable[[Path], bool]
    read: Callable[..., Sweep]
    write: Callable[..., Path]
    description: str


LAYOUTS: dict[str, Layout] = {
    "ultrabones": Layout("ultrabones", ultrabones.detect, ultrabones.read, ultrabones.write,
                         "folder with poses.csv, calibration.json, frames/*.png"),
    "metaio": Layout("metaio", metaio.detect, metaio.read, metaio.write,
                     "PLUS sequence metafile (.mha / .mhd)"),
    "nrrd": Layout("nrrd", nrrd_seq.detect, nrrd_seq.read, nrrd_seq.write,
                   "3D Slicer image sequence (.seq.nrrd) or PLUS .igs.nrrd"),
}


def detect_layout(path: str | os.PathLike) -> str | None:
    """Name of the layout of ``path`` (a key of :data:`LAYOUTS`), or ``None``."""
    p = Path(path)
    for name, layout in LAYOUTS.items():
        if layout.detect(p):
            return name
    return None


def is_sweep_path(path: str | os.PathLike) -> bool:
    """True if ``path`` is a folder or a sequence file that :func:`read_sweep` can read
    (used by ``reconstruct`` to tell a sweep from a point cloud file)."""
    p = Path(path)
    if p.is_dir():
        return True
    return detect_layout(p) is not None


def read_sweep(path: str | os.PathLike, layout: str | None = None, progress: Progress = QUIET,
               **options: Any) -> Sweep:
    """Read a tracked sweep in any registered layout.

    Args:
        path: a sweep folder or a sequence file.
        layout: force a layout (key of :data:`LAYOUTS`); detected from the path by default.
        progress: where the reading is reported (frame by frame for a layout that reads frames
            one at a time).
        **options: passed to the layout's reader (e.g. ``masks=`` for a separate mask stack;
            ``calibration=``, ``transform=``, ``reference=``, ``image_frame=`` for the pose chain of
            MetaIO/NRRD, ``transforms=`` for a NRRD's transform sequences; ``mask_dir=`` for the
            UltraBones100k layout).

    Raises:
        InputError: naming the path, when it does not exist, its layout is unknown, or the reader
        finds it malformed.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    name = layout or detect_layout(p)
    if name is None:
        if p.is_dir():
            raise InputError(f"{p}: not a sweep folder (no poses.csv); supported layouts: "
                             + "; ".join(f"{k}: {v.description}" for k, v in LAYOUTS.items()))
        raise InputError(f"{p}: unknown sweep format {p.suffix!r} (supported: .mha, .mhd, "
                         f".seq.nrrd, or a folder with poses.csv)")
    if name not in LAYOUTS:
        raise InputError(f"unknown sweep layout {name!r}; choose from {', '.join(LAYOUTS)}")
    read = LAYOUTS[name].read
    try:
        if "progress" in inspect.signature(read).parameters:
            return read(p, progress=progress, **options)
        with progress.stage("read sweep", None):
            return read(p, **options)
    except TypeError as exc:  # an option this layout does not take
        if "unexpected keyword" in str(exc):
            raise InputError(f"{p}: {exc} (layout {name})") from None
        raise


def write_sweep(sweep: Sweep, path: str | os.PathLike, layout: str | None = None,
                **options: Any) -> Path:
    """Write a sweep: the layout follows ``path`` (``.mha``/``.mhd`` → metaio, ``.nrrd`` → nrrd,
    anything else → an UltraBones100k-layout folder) unless given."""
    p = Path(path)
    if layout is None:
        suffix = p.suffix.lower()
        layout = "metaio" if suffix in metaio.SUFFIXES else "nrrd" if suffix == ".nrrd" else "ultrabones"
    return LAYOUTS[layout].write(sweep, p, **options)


__all__ = ["LAYOUTS", "Layout", "detect_layout", "is_sweep_path", "read_sweep", "write_sweep"]
