"""Probe calibrations from the files users hold: a PLUS device-set configuration (XML) or a bare
4×4 matrix.

A PLUS configuration keeps the calibration in ``CoordinateDefinitions``::

    <CoordinateDefinitions>
      <Transform From="Image" To="Probe" Matrix="0.0008 0.0854 ... 0 0 0 1" Error="0.58" />
    </CoordinateDefinitions>

``Image`` is the image frame in *pixels* (origin at the first pixel, ``MF`` orientation), so an
``ImageToProbe`` matrix carries the pixel spacing in its columns (possibly different per axis, and a
little sheared). The configuration also says which part of the frame is ultrasound
(``VolumeReconstruction`` ``ClipRectangleOrigin``/``ClipRectangleSize``, pixels), and newer ones
which frames the volume reconstruction uses (``ImageCoordinateFrame``,
``ReferenceCoordinateFrame``). A bare matrix file (16 numbers, row-major, or a ``.npy``) is the
calibration of the image to one named frame (``Probe`` unless told otherwise).
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

XML_SUFFIXES = (".xml",)


@dataclass
class Calibration:
    """Constant transforms and imaging settings from a calibration file.

    Attributes:
        transforms: ``{(From, To): 4×4 matrix}`` (``From``/``To`` coordinate frame names, PLUS style;
            image frames are in pixels, every other frame in mm).
        source: the file, for messages.
        image_frame: the pixel frame named by the file (``VolumeReconstruction
            ImageCoordinateFrame``), or ``None``.
        reference_frame: the output frame named by the file (``ReferenceCoordinateFrame``), or
            ``None``.
        clip_origin_px, clip_size_px: the ultrasound region of the frame, ``(column, row)`` and
            ``(width, height)`` in pixels (``MF`` orientation), or ``None``.
        errors_mm: ``{(From, To): calibration error}`` where the file gives one (``Error=``).
    """

    transforms: dict[tuple[str, str], np.ndarray]
    source: str
    image_frame: str | None = None
    reference_frame: str | None = None
    clip_origin_px: tuple[int, int] | None = None
    clip_size_px: tuple[int, int] | None = None
    errors_mm: dict[tuple[str, str], float] = field(default_factory=dict)

    def describe(self) -> str:
        """``'Image→Probe'``-style list of what the file holds."""
        return ", ".join(f"{a}→{b}" for a, b in self.transforms) or "no transforms"


def parse_numbers(text: str, source: str) -> np.ndarray:
    """16 numbers (or the top 12, row-major) from text with any of ``, ; [ ] ( )`` and ``#``
    comments → 4×4; errors name ``source``."""
    body = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    parts = [p for p in re.split(r"[\s,;\[\]()]+", body) if p]
    try:
        values = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise InputError(f"{source}: cannot parse the matrix numbers {body.strip()[:80]!r}") from None
    if values.size == 12:
        values = np.concatenate([values, [0.0, 0.0, 0.0, 1.0]])
    if values.size != 16:
        raise InputError(f"{source}: expected 16 numbers for a 4×4 matrix (row-major), got {values.size}")
    m = values.reshape(4, 4)
    if not np.isfinite(m).all():
        raise InputError(f"{source}: the matrix contains NaN or Inf")
    return m


def _pair(value: str | None, source: str, what: str) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        a, b = (int(round(float(v))) for v in value.split())
    except ValueError:
        raise InputError(f"{source}: {what} must be two numbers, got {value!r}") from None
    return a, b


def read_plus_config(path: Path) -> Calibration:
    """Transforms and imaging settings of a PLUS device-set configuration file."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"{path}: not a valid XML file ({exc})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    transforms: dict[tuple[str, str], np.ndarray] = {}
    errors: dict[tuple[str, str], float] = {}
    for cd in root.iter("CoordinateDefinitions"):
        for t in cd.iter("Transform"):
            frm, to, text = t.get("From"), t.get("To"), t.get("Matrix")
            if not frm or not to or text is None:
                raise InputError(f"{path}: a CoordinateDefinitions Transform needs From, To and "
                                 f"Matrix attributes (got {dict(t.attrib)})")
            transforms[(frm, to)] = parse_numbers(text, f"{path}: Transform {frm}→{to}")
            try:
                errors[(frm, to)] = float(t.get("Error", "nan"))
            except ValueError:
                pass
    if not transforms:
        raise InputError(f"{path}: no CoordinateDefinitions transforms (is it a PLUS device-set "
                         f"configuration file?)")
    vr = next(root.iter("VolumeReconstruction"), None)
    attrs = {} if vr is None else vr.attrib
    return Calibration(
        transforms=transforms, source=str(path),
        image_frame=attrs.get("ImageCoordinateFrame"), reference_frame=attrs.get("ReferenceCoordinateFrame"),
        clip_origin_px=_pair(attrs.get("ClipRectangleOrigin"), str(path), "ClipRectangleOrigin"),
        clip_size_px=_pair(attrs.get("ClipRectangleSize"), str(path), "ClipRectangleSize"),
        errors_mm={k: v for k, v in errors.items() if np.isfinite(v)})


def read_matrix_file(path: Path, to_frame: str = "Probe", from_frame: str = "Image") -> Calibration:
    """A bare 4×4 calibration (text with 16 numbers row-major, or ``.npy``) as ``from_frame →
    to_frame``."""
    if path.suffix.lower() == ".npy":
        try:
            m = np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
        except (ValueError, OSError) as exc:
            raise InputError(f"{path}: cannot read the matrix ({exc})") from None
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise InputError(f"{path}: expected a finite 4×4 matrix, got shape {m.shape}")
    else:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise InputError(f"{path}: not a text file of 16 numbers (or a .npy / PLUS .xml)") from None
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror})") from None
        m = parse_numbers(text, str(path))
    return Calibration(transforms={(from_frame, to_frame): m}, source=str(path))


def read_calibration(path: str | os.PathLike, to_frame: str = "Probe") -> Calibration:
    """Read ``--calibration FILE``: a PLUS device-set ``.xml`` or a 4×4 matrix file (taken as
    ``Image → to_frame``). Raises :class:`InputError` naming the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such calibration file")
    if p.suffix.lower() in XML_SUFFIXES:
        return read_plus_config(p)
    return read_matrix_file(p, to_frame=to_frame)


__all__ = ["Calibration", "read_calibration", "read_plus_config", "read_matrix_file", "parse_numbers"]
