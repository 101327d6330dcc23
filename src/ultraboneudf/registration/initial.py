"""A pose the user already has: a 4×4 matrix (CT → target, mm) or landmark pairs (`register --init`,
`evaluate --gt-pose`).

Accepted files (every problem is an :class:`~ultraboneudf.errors.InputError` naming the file):

* JSON: a 4×4 list of rows; an object with ``"transform"`` (a 4×4, e.g. an earlier registration's
  output); or an object with ``"ct"`` and ``"target"``, each a list of at least three ``[x, y, z]``
  landmarks (mm, paired by order);
* text (``.txt``, ``.csv``, ``.tfm``-like plain numbers, commas or spaces): 16 numbers (a 4×4, row
  by row) or rows of six numbers ``x y z X Y Z`` (a CT landmark and its target landmark);
* ``.npy``: a ``(4, 4)`` matrix or an ``(N, 6)`` array of landmark pairs.

Landmarks give the least-squares rigid fit of the CT points onto the target points; they must not
all lie on one line.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..sweep import transforms
from . import rigid


def pose_from_landmarks(ct: Any, target: Any, source: str = "landmarks") -> np.ndarray:
    """The rigid ``(4, 4)`` CT → target transform that best maps the ``ct`` landmarks ``(N, 3)``
    onto the ``target`` landmarks ``(N, 3)`` (mm, paired by row, N ≥ 3, not collinear)."""
    try:
        a = np.asarray(ct, dtype=np.float64)
        b = np.asarray(target, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: landmarks must be numbers") from None
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise InputError(f"{source}: expected the same number of CT and target landmarks, each x y z; "
                         f"got {a.shape} and {b.shape}")
    if len(a) < 3:
        raise InputError(f"{source}: {len(a)} landmark pair(s); at least 3 are needed")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError(f"{source}: a landmark holds NaN or Inf")
    for pts, side in ((a, "CT"), (b, "target")):
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if sv[1] <= 1e-6 * max(sv[0], 1e-12):
            raise InputError(f"{source}: the {side} landmarks lie on one line; they cannot fix a rotation")
    return rigid.fit_rigid(a, b)


def check_rigid(matrix: Any, source: str) -> np.ndarray:
    """``matrix`` as a ``(4, 4)`` rigid transform (rotation, translation in mm, last row 0 0 0 1);
    an :class:`InputError` naming ``source`` otherwise."""
    # looser than the tracking's tolerance: a starting pose is often typed or copied with four decimals
    return transforms.check_rigid(matrix, source, tol=1e-3)


def read_init(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, Any]]:
    """The starting pose CT → target ``(4, 4)`` from a file (see the module's text), and a record of
    it for the registration's JSON (``kind``: ``matrix`` or ``landmarks``, the landmarks' count)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file" if not path.exists() else f"{path}: is not a file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".json":
            data = json.loads(path.read_text(encoding="utf-8"))
        elif suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        else:
            text = path.read_text(encoding="utf-8")
            rows = [line.split("#")[0].replace(",", " ").split() for line in text.splitlines()]
            data = [[float(v) for v in row] for row in rows if row]
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the pose ({exc})") from None
    return _interpret(data, str(path))


def _interpret(data: Any, source: str) -> tuple[np.ndarray, dict[str, Any]]:
    if isinstance(data, dict):
        if "transform" in data:
            return check_rigid(data["transform"], source), {"kind": "matrix"}
        if "ct" in data and "target" in data:
            pose = pose_from_landmarks(data["ct"], data["target"], source)
            return pose, {"kind": "landmarks", "pairs": len(data["ct"])}
        raise InputError(f"{source}: a JSON pose needs \"transform\" (4×4) or \"ct\" and \"target\" "
                         f"landmark lists")
    if isinstance(data, list):
        lengths = {len(row) if isinstance(row, list) else -1 for row in data}
        if lengths == {6}:
            arr = np.asarray(data, dtype=np.float64)
        elif lengths == {16}:
            arr = np.asarray(data[0] if len(data) == 1 else data, dtype=np.float64)
        else:
            try:
                arr = np.asarray(data, dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"{source}: expected a 4×4 matrix or rows of six numbers "
                                 f"(CT x y z, target x y z)") from None
    else:
        arr = np.asarray(data, dtype=np.float64)
    if arr.size == 16 and arr.shape in ((4, 4), (16,), (1, 16)):
        return check_rigid(arr.reshape(4, 4), source), {"kind": "matrix"}
    if arr.ndim == 2 and arr.shape[1] == 6:
        return pose_from_landmarks(arr[:, :3], arr[:, 3:], source), {"kind": "landmarks", "pairs": len(arr)}
    raise InputError(f"{source}: expected a 4×4 matrix (16 numbers) or rows of six numbers "
                     f"(CT x y z, target x y z), got shape {arr.shape}")
