"""Datasets as manifests: a CSV file listing reconstruction units.

Columns (header required, order free): ``id`` (unique), ``specimen`` (units of one specimen are
averaged together, §6.1), ``input`` (a point cloud file in mm — ``.npz`` may carry ``probe`` beside
``points`` — or a tracked sweep), ``gt`` (the ground-truth mesh, mm, same frame) and optionally
``pseudo_gt_mm`` (τ of the pseudo ground truth, §6.2: only ground truth within τ of the input is
scored; empty = the whole mesh). Paths are relative to the manifest's folder; nothing outside it
is assumed.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..io import atomic_write_bytes

COLUMNS = ("id", "specimen", "input", "gt", "pseudo_gt_mm")
PLAIN_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
"""An id names a folder of the runner's results: a plain name, never a path."""


@dataclass(frozen=True)
class Unit:
    """One reconstruction unit of a manifest (paths absolute once read)."""

    id: str
    specimen: str
    input: Path
    gt: Path
    pseudo_gt_mm: float | None = None


def read_manifest(path: str | os.PathLike) -> list[Unit]:
    """The units of a manifest CSV; :class:`InputError` naming the file and line for a missing
    column, an empty or duplicate id, an id that is not a plain name (``../x``, ``/abs/x``: the
    runner's folders are named after it), a file that does not exist or a bad τ."""
    from ..io import check_input

    path = check_input(path, "manifest file")
    try:
        rows = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8-sig"))))
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (cannot decode as UTF-8)") from None
    header = set(rows[0]) if rows else set()
    missing = [c for c in COLUMNS[:4] if c not in header]
    if missing:
        raise InputError(f"{path}: the manifest needs the columns {', '.join(COLUMNS[:4])} "
                         f"(missing: {', '.join(missing)})")
    units, seen = [], set()
    for line, row in enumerate(rows, start=2):
        uid = (row.get("id") or "").strip()
        if not uid or uid in seen:
            raise InputError(f"{path}: line {line}: {'empty' if not uid else 'duplicate'} id {uid!r}")
        if not PLAIN_ID.fullmatch(uid) or ".." in uid:
            raise InputError(f"{path}: line {line}: id {uid!r} is not a plain name (up to 100 letters, "
                             f"digits, '.', '_' or '-'; no path): the results are stored under it")
        seen.add(uid)
        files = {}
        for key in ("input", "gt"):
            value = (row.get(key) or "").strip()
            target = (path.parent / value).resolve()
            if not value or not target.exists():
                raise InputError(f"{path}: line {line}: {key} {value!r} does not exist")
            files[key] = target
        tau_text = (row.get("pseudo_gt_mm") or "").strip()
        try:
            tau = float(tau_text) if tau_text else None
        except ValueError:
            raise InputError(f"{path}: line {line}: pseudo_gt_mm {tau_text!r} is not a number") from None
        if tau is not None and not (math.isfinite(tau) and tau > 0):
            raise InputError(f"{path}: line {line}: pseudo_gt_mm must be a positive number of mm")
        units.append(Unit(uid, (row.get("specimen") or "").strip() or uid, files["input"], files["gt"], tau))
    if not units:
        raise InputError(f"{path}: the manifest lists no units")
    return units


def write_manifest(units: list[Unit], path: str | os.PathLike) -> None:
    """Write ``units`` as a manifest at ``path`` (atomically), with paths relative to its folder."""
    path = Path(path)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for u in units:
        w.writerow([u.id, u.specimen, os.path.relpath(u.input, path.parent), os.path.relpath(u.gt, path.parent),
                    "" if u.pseudo_gt_mm is None else repr(u.pseudo_gt_mm)])
    atomic_write_bytes(path, buf.getvalue().encode("utf-8"))
