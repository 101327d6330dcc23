"""The UltraBones100k sample layout: ``frames/*.png``, ``poses.csv``, ``calibration.json``.

::

    SWEEP/
      poses.csv           timestamp,space_factor,x,y,z,euler_x,euler_y,euler_z   (one row per frame)
      calibration.json    translation_mm, euler_xyz_deg (or matrix), pixel_spacing_mm, pixel_center_offset
      frames/<timestamp>.png     B-mode frames (optional when masks are given)
      masks/<timestamp>.png      bone masks (optional; or masks.npy, (F, H, W))

Pixel → world (mm): ``T_track · T_calib · diag(s, s, 1, 1) · [c + 0.5, r + 0.5, 0, 1]ᵀ`` with
``T_track`` from the row (extrinsic xyz Euler degrees + translation mm) and ``T_calib`` from
``calibration.json``. ``s`` is the row's ``space_factor``; without that column the calibration's
``pixel_spacing_mm`` (``[sx, sy]``) is used.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from ...errors import InputError
from ...io import atomic_write_bytes, save_json
from ..model import Sweep
from ..transforms import check_rigid, euler_from_rigid, invert_rigid, rigid_from_euler
from ...progress import QUIET, Progress
from .images import load_mask_stack, read_stack, write_png

POSE_COLUMNS = ("timestamp", "x", "y", "z", "euler_x", "euler_y", "euler_z")
FRAME_DIR = "frames"
DEFAULT_MASK_DIR = "masks"


def detect(path: Path) -> bool:
    """A folder holding ``poses.csv``."""
    return path.is_dir() and (path / "poses.csv").is_file()


def read_calibration(path: Path) -> dict:
    """Parse ``calibration.json`` into ``{'matrix': 4×4 rigid, 'spacing': (2,) or None, 'offset',
    'image_size': (W, H) or None}``; errors name the file."""
    if not path.is_file():
        raise InputError(f"{path}: missing calibration file (the probe calibration of the sweep)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object")
    try:
        if "matrix" in data:
            matrix = np.asarray(data["matrix"], dtype=np.float64).reshape(4, 4)
        elif "translation_mm" in data and "euler_xyz_deg" in data:
            t = np.asarray(data["translation_mm"], dtype=np.float64).reshape(3)
            e = np.asarray(data["euler_xyz_deg"], dtype=np.float64).reshape(3)
            matrix = rigid_from_euler(t, e)
        else:
            raise InputError(f"{path}: needs 'translation_mm' and 'euler_xyz_deg' (or a 4×4 'matrix')")
        spacing = data.get("pixel_spacing_mm")
        if spacing is not None:
            spacing = np.asarray(spacing, dtype=np.float64).reshape(-1)
            spacing = np.repeat(spacing, 2) if spacing.size == 1 else spacing.reshape(2)
        offset = float(data.get("pixel_center_offset", 0.5))
        size = data.get("image_size_px")
        size = None if size is None else tuple(int(v) for v in size)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: malformed calibration ({exc})") from None
    matrix = check_rigid(matrix, f"{path}: calibration")
    if spacing is not None and not (np.isfinite(spacing).all() and (spacing > 0).all()):
        raise InputError(f"{path}: pixel_spacing_mm must be positive, got {spacing.tolist()}")
    return {"matrix": matrix, "spacing": spacing, "offset": offset, "image_size": size,
            "raw": data}


def _read_poses(path: Path) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """``(names, T_track (F,4,4), space_factor (F,) or None)`` from ``poses.csv``."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file") from None
    reader = csv.reader(io.StringIO(text))
    rows = [r for r in reader if r and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path}: empty pose file")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)} "
                         f"(expected {','.join(POSE_COLUMNS)}, optionally space_factor)")
    col = {name: header.index(name) for name in header}
    has_s = "space_factor" in col
    names, mats, spacing = [], [], []
    for line_no, row in enumerate(rows[1:], start=2):
        try:
            vals = {k: float(row[col[k]]) for k in POSE_COLUMNS[1:]}
            if has_s:
                spacing.append(float(row[col["space_factor"]]))
        except (ValueError, IndexError):
            raise InputError(f"{path}: line {line_no}: cannot parse the pose {','.join(row)[:80]!r}") from None
        if not all(np.isfinite(v) for v in vals.values()):
            raise InputError(f"{path}: line {line_no}: pose contains NaN or Inf")
        names.append(row[col["timestamp"]].strip())
        mats.append(rigid_from_euler([vals["x"], vals["y"], vals["z"]],
                                     [vals["euler_x"], vals["euler_y"], vals["euler_z"]]))
    if not names:
        raise InputError(f"{path}: no pose rows")
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise InputError(f"{path}: timestamp {dup} appears more than once")
    sf = np.asarray(spacing, dtype=np.float64) if has_s else None
    if sf is not None and not (np.isfinite(sf).all() and (sf > 0).all()):
        bad = int(np.flatnonzero(~(np.isfinite(sf) & (sf > 0)))[0])
        raise InputError(f"{path}: line {bad + 2}: space_factor must be a positive number of mm per pixel")
    return names, np.stack(mats), sf


def _timestamp_value(name: str, index: int) -> float:
    try:
        return float(name)
    except ValueError:
        return float(index)


def read(path: str | os.PathLike, masks: str | os.PathLike | None = None,
         mask_dir: str = DEFAULT_MASK_DIR, load_images: bool = True, progress: Progress = QUIET) -> Sweep:
    """Read a sweep folder in the UltraBones100k layout.

    Args:
        path: the folder.
        masks: explicit masks (folder of PNGs or ``.npy``/``.npz``), overriding ``mask_dir``.
        mask_dir: sub-folder (or ``<mask_dir>.npy`` file) of masks to load when present.
        load_images: read ``frames/`` (set False to read poses and masks only).
        progress: reports the frames read.

    Raises:
        InputError: naming the file, for a missing/unreadable frame, a pose count that differs from
        the frame count, a non-rigid calibration, no pixel spacing, or malformed rows.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: not a folder")
    poses_path = root / "poses.csv"
    if not poses_path.is_file():
        raise InputError(f"{poses_path}: missing pose file")
    calib = read_calibration(root / "calibration.json")
    names, tracks, sf = _read_poses(poses_path)
    n = len(names)
    if sf is not None:
        spacing = np.stack([sf, sf], axis=1)
    elif calib["spacing"] is not None:
        spacing = np.broadcast_to(calib["spacing"], (n, 2)).copy()
    else:
        raise InputError(f"{poses_path}: no pixel spacing (neither a space_factor column nor "
                         f"pixel_spacing_mm in {root / 'calibration.json'})")

    frame_dir = root / FRAME_DIR
    images = None
    frame_files: list[Path] = []
    if frame_dir.is_dir():
        on_disk = {p.stem: p for p in frame_dir.iterdir() if not p.is_dir() and not p.name.startswith(".")}
        for line_no, name in enumerate(names, start=2):
            if name not in on_disk:
                raise InputError(f"{frame_dir / (name + '.png')}: missing frame (listed in "
                                 f"{poses_path} line {line_no})")
            frame_files.append(on_disk[name])
        extra = sorted(set(on_disk) - set(names))
        if extra:
            raise InputError(f"{poses_path}: {n} poses but {frame_dir} holds {len(on_disk)} frames "
                             f"(no pose for {', '.join(e for e in extra[:3])}"
                             f"{' …' if len(extra) > 3 else ''})")

    size = calib["image_size"]
    if load_images and frame_files:
        images = read_stack(frame_files, size, progress)
        size = (images.shape[2], images.shape[1])

    mask_arr = None
    mask_source = Path(masks) if masks is not None else None
    if mask_source is None:
        for cand in (root / mask_dir, root / f"{mask_dir}.npy", root / f"{mask_dir}.npz"):
            if cand.exists():
                mask_source = cand
                break
    if mask_source is not None:
        stems = [Path(p).stem for p in frame_files] if frame_files else names
        mask_arr = load_mask_stack(mask_source, n, size, stems)
        size = (mask_arr.shape[2], mask_arr.shape[1])
    if images is None and mask_arr is None:
        if load_images:
            raise InputError(f"{frame_dir}: missing frames folder (and no masks in {root / mask_dir})")
        if size is None:
            raise InputError(f"{root}: no frames and no image_size_px in calibration.json")

    image_to_world = np.stack([check_rigid(t, f"{poses_path}: line {i + 2}") @ calib["matrix"]
                               for i, t in enumerate(tracks)])
    return Sweep(
        image_to_world=image_to_world, spacing_mm=spacing, image_size=size, images=images,
        masks=mask_arr, timestamps=np.array([_timestamp_value(nm, i) for i, nm in enumerate(names)]),
        frame_names=[p.name for p in frame_files] if frame_files else [f"{nm}.png" for nm in names],
        pixel_offset=calib["offset"], orientation="MF", source=str(root),
        meta={"layout": "ultrabones", "calibration": calib["matrix"], "timestamp_strings": names},
    )


def _fmt(v: float) -> str:
    return repr(float(v))


def write(sweep: Sweep, folder: str | os.PathLike, calibration: np.ndarray | None = None,
          names: list[str] | None = None, write_images: bool = True,
          mask_sets: Mapping[str, np.ndarray] | None = None,
          extra_calibration: Mapping[str, object] | None = None) -> Path:
    """Write ``sweep`` in the UltraBones100k layout (every file atomically).

    Args:
        sweep: the sweep; its pixel → world maps are reproduced exactly.
        folder: output folder (created).
        calibration: the 4×4 rigid ``T_calib`` to factor out of ``image_to_world``
            (``T_track = image_to_world · translate(Δo) · T_calib⁻¹``); identity by default.
        names: file stems / timestamps, one per frame (default: the sweep's timestamps as
            integers when they are whole numbers, else ``000000``, ``000001``, …).
        write_images: write ``frames/`` (needs ``sweep.images``).
        mask_sets: extra mask stacks to write, ``{sub-folder: (F, H, W) bool}``; the sweep's own
            masks go to ``masks/`` unless this mapping names ``masks``.
        extra_calibration: extra keys to store in ``calibration.json``.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    n = sweep.n_frames
    calib = np.eye(4) if calibration is None else check_rigid(calibration, "calibration")
    if names is None:
        ts = sweep.timestamps
        if np.all(np.isfinite(ts)) and np.all(ts == np.round(ts)) and len(set(ts.tolist())) == n:
            names = [str(int(t)) for t in ts]
        else:
            names = [f"{i:06d}" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} frames")
    sp = sweep.spacing_mm
    isotropic = bool(np.all(sp[:, 0] == sp[:, 1]))
    constant = bool(np.all(sp == sp[0]))
    if not isotropic and not constant:
        raise ValueError("the UltraBones100k layout needs square pixels or one spacing for all frames")
    if np.any(sweep.shear_deg != 0):
        raise ValueError("the UltraBones100k layout has no shear: write a sheared calibration's sweep "
                         "as .mha or .seq.nrrd")
    # pixel centres at +0.5 in this layout: fold the sweep's own offset into the transform
    lines = ["timestamp,space_factor,x,y,z,euler_x,euler_y,euler_z" if isotropic
             else "timestamp,x,y,z,euler_x,euler_y,euler_z"]
    inv_calib = invert_rigid(calib)
    for i in range(n):
        shift = np.eye(4)
        shift[:2, 3] = (sweep.pixel_offset - 0.5) * sp[i]
        track = sweep.image_to_world[i] @ shift @ inv_calib
        t, e = euler_from_rigid(track)
        vals = [names[i]] + ([_fmt(sp[i, 0])] if isotropic else []) + [_fmt(v) for v in (*t, *e)]
        lines.append(",".join(vals))
    atomic_write_bytes(out / "poses.csv", ("\n".join(lines) + "\n").encode("utf-8"))
    ct, ce = euler_from_rigid(calib)
    cal: dict[str, object] = {
        "description": "Probe calibration: maps image-plane millimetres to the tracked probe frame.",
        "translation_mm": [float(v) for v in ct],
        "euler_xyz_deg": [float(v) for v in ce],
        "euler_convention": "extrinsic xyz, degrees (scipy Rotation.from_euler('xyz', angles, degrees=True))",
        "pixel_spacing_mm": [float(sp[0, 0]), float(sp[0, 1])],
        "pixel_center_offset": 0.5,
        "image_size_px": [sweep.width, sweep.height],
    }
    if extra_calibration:
        cal.update(extra_calibration)
    save_json(cal, out / "calibration.json")
    if write_images:
        if sweep.images is None:
            raise ValueError("the sweep has no images to write")
        for i in range(n):
            write_png(out / FRAME_DIR / f"{names[i]}.png", sweep.images[i])
    sets = dict(mask_sets or {})
    if sweep.masks is not None and DEFAULT_MASK_DIR not in sets:
        sets[DEFAULT_MASK_DIR] = sweep.masks
    for sub, stack in sets.items():
        stack = np.asarray(stack)
        if stack.shape != (n, sweep.height, sweep.width):
            raise ValueError(f"mask set {sub!r} has shape {stack.shape}")
        for i in range(n):
            write_png(out / sub / f"{names[i]}.png", stack[i] != 0)
    return out
