"""The pixel → reference chain of a tracked sequence, resolved the way PLUS's transform repository
does it.

A PLUS recording stores tracking transforms per frame (``ProbeToTracker``, ``ReferenceToTracker``,
…; sometimes ``ImageToReference`` directly) and keeps the probe calibration (``ImageToProbe``) in
its configuration file. Every transform ``AToB`` is an edge between coordinate frames ``A`` and
``B`` (usable both ways, inverted); the pose of the pixels is the product along the path from the
pixel frame to the reference frame, e.g.::

    ImageToReference = ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe

Rules:

* Frames whose name ends in ``Image`` are pixel frames. A transform between two pixel frames
  (``ImageToCroppedImage``) must be a fixed in-plane pixel offset: it is a crop, never a pose.
  When the file holds such an offset from ``Image`` to a frame nothing else connects to, the
  stored pixels are that crop (``CroppedImage``), and the chain starts there.
* The chain must contain at least one per-frame transform that is not a pixel offset (the
  tracking), or the frames have no pose.
* The reference is ``--reference``, else the configuration's ``ReferenceCoordinateFrame``, else
  ``Reference`` when reachable, else ``Tracker`` (with a warning: the points then move with the
  camera, not the patient).
* ``--transform NAME`` forces that per-frame transform into the chain.
* A frame is used when every per-frame transform of the chain has status ``OK`` in it.
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .calibration import Calibration
from .model import SweepWarning
from .transforms import (
    check_rigid,
    decompose_pixel_transform,
    invert_affine,
    is_pixel_offset,
    parse_matrix,
)

RIGID_TRACKING_TOL = 1e-3
"""Largest accepted ``|RᵀR − I|`` of a mm → mm transform in the chain: tracker output and
configuration files carry 4–6 significant digits."""


def split_transform_name(name: str) -> tuple[str, str] | None:
    """``'ProbeToTracker'`` → ``('Probe', 'Tracker')``; ``None`` when the name has no unique
    ``To`` followed by a capital letter (PLUS naming), e.g. ``'ToolToTracker'`` → ``('Tool',
    'Tracker')``."""
    name = name[:-len("Transform")] if name.endswith("Transform") else name
    if name.endswith("-Seq"):  # Slicer names a sequence node '<name>-Seq'
        name = name[:-4]
    cuts = [i for i in range(1, len(name) - 2)
            if name[i:i + 2] == "To" and name[i + 2].isupper() and name[0].isupper()]
    if len(cuts) != 1:
        return None
    return name[:cuts[0]], name[cuts[0] + 2:]


def is_pixel_frame(frame: str) -> bool:
    """Frames measured in pixels: ``Image``, ``CroppedImage``, …"""
    return frame.endswith("Image")


class FrameTransforms:
    """Per-frame transforms of a sequence file (``Seq_FrameNNNN_<Name>Transform`` fields), parsed
    when a chain uses them.

    Args:
        per_frame: ``{frame index: {field name: value}}`` (see ``metaio.frame_fields``).
        n_frames: number of images in the file.
        source: the file holding the fields (for messages).
    """

    def __init__(self, per_frame: dict[int, dict[str, str]], n_frames: int, source: str | Path):
        self.per_frame = per_frame
        self.n_frames = int(n_frames)
        self.source = str(source)
        self._cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def names(self) -> list[str]:
        """Transform names (without the ``Transform`` suffix) present in any frame."""
        out = {k[:-len("Transform")] for f in self.per_frame.values() for k in f
               if k.endswith("Transform")}
        return sorted(out)

    def matrices(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(matrices (F, 4, 4), ok (F,) bool)`` of transform ``name`` (status ``OK`` or none).

        Raises :class:`InputError` when some image has no such field (or fields exist for frames
        beyond the last image), or a matrix does not parse."""
        if name in self._cache:
            return self._cache[name]
        key = f"{name}Transform"
        n = self.n_frames
        have = sorted(i for i, f in self.per_frame.items() if key in f)
        if have != list(range(n)):
            absent = sorted(set(range(n)) - set(have))
            extra = sorted(set(have) - set(range(n)))
            detail = (f"no transform for frame {absent[0]}" if absent
                      else f"transforms for frames beyond the last image (frame {extra[0]})")
            raise InputError(f"{self.source}: {n} frames (DimSize) but {len(have)} {key} fields ({detail})")
        mats = np.empty((n, 4, 4))
        ok = np.ones(n, dtype=bool)
        for i in range(n):
            f = self.per_frame[i]
            ok[i] = f.get(f"{key}Status", "OK").strip().upper() in ("OK", "VALID")
            if ok[i]:
                mats[i] = parse_matrix(f[key], f"{self.source}: Seq_Frame{i:04d}_{key}")
            else:
                mats[i] = np.eye(4)
        self._cache[name] = (mats, ok)
        return mats, ok


@dataclass
class Step:
    """One transform of a resolved chain, applied from ``frm`` to ``to``."""

    name: str             # PLUS name as stored, e.g. 'ReferenceToTracker'
    frm: str
    to: str
    inverted: bool        # the stored transform maps to → frm
    origin: str           # 'frame' (per-frame, in the sequence file) or 'calibration'
    pixel_offset: bool = False

    def label(self) -> str:
        return self.name + ("⁻¹" if self.inverted else "")


@dataclass
class PoseChain:
    """A resolved chain: per-frame pixel → reference matrices and how they were made.

    Attributes:
        matrices: ``(F, 4, 4)`` pixel ``[c, r, 0, 1]`` → reference mm (affine: scale in the columns).
        ok: ``(F,)`` frames whose every per-frame transform of the chain is valid.
        steps: the transforms from the pixel frame to the reference, in order of application.
        pixel_frame, reference_frame: the chain's two ends.
        notes: sentences for the log (e.g. that the stored frames are a crop).
    """

    matrices: np.ndarray
    ok: np.ndarray
    steps: list[Step]
    pixel_frame: str
    reference_frame: str
    calibration_source: str | None = None
    notes: list[str] = field(default_factory=list)
    crop_offset_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """``(column, row)`` of the stored pixel ``(0, 0)`` in the ``Image`` frame (non-zero for a crop)."""

    def formula(self) -> str:
        """``'ReferenceToTracker⁻¹ · ProbeToTracker · ImageToProbe'`` (matrix product order)."""
        return " · ".join(s.label() for s in reversed(self.steps))

    def as_dict(self) -> dict:
        """JSON-ready summary (for sidecars)."""
        return {"pixel_frame": self.pixel_frame, "reference_frame": self.reference_frame,
                "chain": self.formula(), "calibration": self.calibration_source,
                "frames_used": int(self.ok.sum()), "frames": int(len(self.ok))}


@dataclass
class _Edge:
    name: str
    frm: str
    to: str
    origin: str
    matrix: np.ndarray | None = None   # calibration edges


def _edges(frames: FrameTransforms, calibration: Calibration | None) -> list[_Edge]:
    edges: dict[frozenset, _Edge] = {}
    unnamed = []
    for name in frames.names():
        pair = split_transform_name(name)
        if pair is None or pair[0] == pair[1]:
            unnamed.append(name)
            continue
        edges[frozenset(pair)] = _Edge(name, pair[0], pair[1], "frame")
    if unnamed:
        warnings.warn(f"{frames.source}: transform name(s) {', '.join(unnamed)} do not read as "
                      f"<From>To<To>; not used", SweepWarning, stacklevel=4)
    if calibration is not None:
        for (a, b), m in calibration.transforms.items():
            key = frozenset((a, b))
            if key in edges and edges[key].origin == "frame":
                warnings.warn(f"{calibration.source}: its {a}To{b} replaces the sequence's per-frame "
                              f"{edges[key].name}Transform", SweepWarning, stacklevel=4)
            edges[key] = _Edge(f"{a}To{b}", a, b, "calibration", m)
    return list(edges.values())


def _paths(edges: list[_Edge], start: str) -> dict[str, list[tuple[_Edge, bool]]]:
    """Shortest paths (fewest transforms) from ``start`` to every reachable frame."""
    adj: dict[str, list[tuple[str, _Edge, bool]]] = {}
    for e in edges:
        adj.setdefault(e.frm, []).append((e.to, e, False))
        adj.setdefault(e.to, []).append((e.frm, e, True))
    best: dict[str, list[tuple[_Edge, bool]]] = {start: []}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        # calibration edges first, so that a config's transform wins ties over a file's
        for nxt, e, inv in sorted(adj.get(node, []), key=lambda t: (t[1].origin != "calibration", t[1].name)):
            if nxt not in best:
                best[nxt] = best[node] + [(e, inv)]
                queue.append(nxt)
    return best


def _holdings(frames: FrameTransforms, calibration: Calibration | None) -> str:
    held = f"the file holds {', '.join(n + 'Transform' for n in frames.names()) or 'no transforms'}"
    if calibration is not None:
        held += f"; {Path(calibration.source).name} holds {calibration.describe()}"
    return held


def resolve_chain(frames: FrameTransforms, calibration: Calibration | None = None,
                  transform: str | None = None, reference: str | None = None,
                  image_frame: str | None = None) -> PoseChain:
    """Resolve and compose the pixel → reference chain of a sequence.

    Args:
        frames: the file's per-frame transforms.
        calibration: constant transforms (``--calibration``), or ``None``.
        transform: a per-frame transform the chain must use (``ImageToReference``,
            ``ProbeToTracker``, …; the ``Transform`` suffix is optional).
        reference: the output frame (default: see the module docstring).
        image_frame: the frame of the stored pixels (default ``Image``, or the crop frame).

    Raises:
        InputError: naming the file, when no chain exists (saying what is missing), the chain has
        no tracking transform, a transform in it is malformed or not rigid, or no frame is valid.
    """
    src = frames.source
    edges = _edges(frames, calibration)
    notes: list[str] = []
    frames_of = {f for e in edges for f in (e.frm, e.to)}

    # the pixel frame
    pixel = image_frame or (calibration.image_frame if calibration else None)
    if pixel is None:
        pixel = "Image"
        crops = [e for e in edges if e.origin == "frame" and "Image" in (e.frm, e.to)
                 and is_pixel_frame(e.frm) and is_pixel_frame(e.to)]
        for e in crops:
            other = e.to if e.frm == "Image" else e.frm
            degree = sum(other in (x.frm, x.to) for x in edges)
            mats, valid = frames.matrices(e.name)
            if degree == 1 and is_pixel_offset(mats[valid]):
                pixel = other
                notes.append(f"{e.name}Transform is a fixed pixel offset: the stored frames are the "
                             f"{other} crop, mapped back to Image through it")
    if pixel not in frames_of:
        if calibration is None:
            tracked = sorted({e.frm for e in edges if e.origin == "frame" and not is_pixel_frame(e.frm)
                              and e.frm not in ("Reference", "Stylus", "Tracker")})
            probe = "Probe" if "Probe" in tracked or not tracked else tracked[0]
            raise InputError(f"{src}: no per-frame ImageTo…Transform and no calibration, so the image "
                             f"pixels have no pose; {_holdings(frames, calibration)}; give the probe "
                             f"calibration Image→{probe} with --calibration (PLUS device-set .xml, or "
                             f"a 4×4 matrix file)")
        raise InputError(f"{src}: no transform starts from the image pixels ({pixel}); "
                         f"{_holdings(frames, calibration)}")
    paths = _paths(edges, pixel)

    forced: _Edge | None = None
    if transform:
        want = transform[:-len("Transform")] if transform.endswith("Transform") else transform
        forced = next((e for e in edges if e.name == want and e.origin == "frame"), None)
        if forced is None:
            raise InputError(f"{src}: no per-frame {want}Transform (found: "
                             f"{', '.join(frames.names()) or 'none'})")

    def route(target: str) -> list[tuple[_Edge, bool]] | None:
        if forced is None:
            return paths.get(target)
        best = None
        for a, b, inv in ((forced.frm, forced.to, False), (forced.to, forced.frm, True)):
            head = paths.get(a)
            if head is None or any(e is forced for e, _ in head):
                continue
            tail = _paths([e for e in edges if e is not forced], b).get(target)
            if tail is None:
                continue
            cand = head + [(forced, inv)] + tail
            if best is None or len(cand) < len(best):
                best = cand
        return best

    # the reference frame
    ref = reference or (calibration.reference_frame if calibration else None)
    path = None
    if ref is None:
        for cand in ("Reference", "Tracker"):
            path = route(cand)
            if path is not None:
                ref = cand
                break
        if ref is None and forced is not None:
            ref = forced.to
            path = route(ref)
    else:
        path = route(ref)
    if path is None or ref is None:
        target = ref or "Reference"
        hint = ""
        has_probe = any("Probe" in (e.frm, e.to) for e in edges)
        has_image_probe = any({e.frm, e.to} == {"Image", "Probe"} for e in edges)
        if has_probe and not has_image_probe:
            hint = ("; the probe calibration ImageToProbe is missing: give the PLUS device-set .xml "
                    "or a 4×4 matrix file with --calibration")
        raise InputError(f"{src}: no chain of transforms from the image pixels ({pixel}) to {target}"
                         + (f" through {forced.name}Transform" if forced else "")
                         + f"; {_holdings(frames, calibration)}{hint}")

    # steps, validation and composition
    pixel_side = {pixel}
    steps: list[Step] = []
    n = frames.n_frames
    total = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    ok = np.ones(n, dtype=bool)
    node = pixel
    crop = np.eye(4)
    for e, inv in path:
        nxt = e.frm if inv else e.to
        if e.origin == "frame":
            mats, valid = frames.matrices(e.name)
            ok &= valid
        else:
            mats, valid = np.broadcast_to(e.matrix, (n, 4, 4)), np.ones(n, dtype=bool)
        offset = is_pixel_frame(node) and is_pixel_frame(nxt)
        label = (f"{calibration.source}: Transform {e.frm}→{e.to}" if e.origin == "calibration"
                 else f"{src}: {e.name}Transform")
        if offset:
            if not is_pixel_offset(mats[valid]):
                raise InputError(f"{label} maps one pixel frame to another but is not a fixed "
                                 f"in-plane pixel offset")
            pixel_side.add(nxt)
            crop = (invert_affine(mats[valid][0]) if inv else mats[valid][0]) @ crop
        elif node in pixel_side or nxt in pixel_side:
            # pixels → mm: scale (per axis) and a little shear allowed, nothing else
            first = np.flatnonzero(valid)
            for i in (first if e.origin == "frame" else first[:1]):
                where = f"{src}: Seq_Frame{i:04d}_{e.name}Transform" if e.origin == "frame" else label
                decompose_pixel_transform(mats[i], where)
        else:
            first = np.flatnonzero(valid)
            for i in (first if e.origin == "frame" else first[:1]):
                where = f"{src}: Seq_Frame{i:04d}_{e.name}Transform" if e.origin == "frame" else label
                check_rigid(mats[i], where, tol=RIGID_TRACKING_TOL)
        step_m = invert_affine(mats) if inv else mats
        total = np.einsum("fij,fjk->fik", step_m, total)
        steps.append(Step(e.name, node, nxt, inv, e.origin, offset))
        node = nxt
    poses = [s for s in steps if s.origin == "frame" and not s.pixel_offset]
    if not poses:
        raise InputError(f"{src}: the chain {pixel}→{ref} ("
                         f"{' · '.join(s.label() for s in reversed(steps))}) holds no per-frame "
                         f"tracking transform, so the frames have no pose")
    if not ok.any():
        used = ", ".join(s.name for s in steps if s.origin == "frame")
        raise InputError(f"{src}: no frame has a valid pose (status INVALID in every frame for {used})")
    if ref == "Tracker" and reference is None:
        warnings.warn(f"{src}: no Reference frame in the chain: the points are in the Tracker "
                      f"(camera) frame, so patient motion during the sweep is not compensated",
                      SweepWarning, stacklevel=3)
    bad = int((~ok).sum())
    if bad:
        first_bad = int(np.flatnonzero(~ok)[0])
        warnings.warn(f"{src}: skipped {bad} frame(s) with an INVALID transform status in the chain "
                      f"(first: frame {first_bad})", SweepWarning, stacklevel=3)
    return PoseChain(total, ok, steps, pixel, ref,
                     calibration.source if calibration and any(s.origin == "calibration" for s in steps)
                     else None, notes, crop[:2, 3].copy())


def frames_coplanar(pixel_to_world: np.ndarray, image_size: tuple[int, int],
                    tol_mm: float = 1e-3) -> tuple[bool, float]:
    """Whether every frame lies in one plane: ``(coplanar, thickness_mm)``.

    ``thickness_mm`` is the largest distance of any frame corner from the best-fitting plane of
    all corners (0 for a single frame, or for poses that never leave the image plane)."""
    w, h = image_size
    corners = np.array([[0, 0, 0, 1], [w - 1, 0, 0, 1], [0, h - 1, 0, 1], [w - 1, h - 1, 0, 1]], float)
    pts = np.einsum("fij,kj->fki", np.asarray(pixel_to_world), corners)[..., :3].reshape(-1, 3)
    centred = pts - pts.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][-1]
    thickness = float(np.abs(centred @ normal).max())
    return thickness <= tol_mm, thickness


__all__ = ["FrameTransforms", "PoseChain", "Step", "resolve_chain", "split_transform_name",
           "frames_coplanar", "is_pixel_frame"]
