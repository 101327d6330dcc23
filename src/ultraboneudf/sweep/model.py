"""The in-memory tracked sweep: frames (B-mode images and/or bone masks) with their poses.

Geometry of one frame ``i`` (all lengths in millimetres)::

    world = image_to_world[i] · P(spacing_mm[i], pixel_offset) · [c, r, 0, 1]ᵀ

where ``c`` is the pixel column (0 at the left, the lateral direction), ``r`` the pixel row (0 at
the top, where the probe touches the skin; the beams run down the columns), and
``P = diag(sx, sy, 1, 1) · translate(o, o, 0)`` places the pixel centre ``(c, r)`` at image-plane
millimetres ``((c + o)·sx, (r + o)·sy, 0)`` (a calibration with slightly non-perpendicular image
axes adds a shear, see :func:`~ultraboneudf.sweep.transforms.pixel_to_image_matrix`).
``image_to_world[i]`` is rigid (rotation + translation, mm → mm). The UltraBones100k layout puts
pixel centres at ``o = 0.5``; PLUS/ITK/Slicer put the centre of the first pixel at the origin,
``o = 0``. :meth:`Sweep.pixel_to_world` gives the whole
product, which is what every reader and writer round-trips exactly.

The world frame is whatever frame the input's transforms map to (the CT frame for the
UltraBones100k sample, the tracker/reference frame for PLUS files); it is carried unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..errors import SweepWarning  # noqa: F401  (re-exported: sweep.model.SweepWarning)
from .transforms import pixel_to_image_matrix


@dataclass
class Sweep:
    """A tracked freehand ultrasound sweep held in memory.

    Attributes:
        image_to_world: ``(F, 4, 4)`` float64, rigid transforms from image-plane mm to world mm.
        spacing_mm: ``(F, 2)`` float64, pixel size (column/lateral ``sx``, row/axial ``sy``) in mm
            (a scalar or a pair is broadcast to every frame).
        image_size: ``(width, height)`` of every frame in pixels.
        images: ``(F, H, W)`` B-mode intensities (usually ``uint8``), or ``None`` for a mask-only sweep.
        masks: ``(F, H, W)`` bool bone masks, or ``None``.
        timestamps: ``(F,)`` float64, in the source's unit (seconds for PLUS; the UltraBones100k
            sample uses integer frame clock values).
        frame_names: one label per frame (file name or ``Seq_FrameNNNN``), used in messages.
        pixel_offset: ``o`` in the formula above (0.5 UltraBones100k, 0.0 PLUS/Slicer).
        orientation: PLUS ultrasound image orientation of the frames as held (``MF`` canonical).
        source: the path the sweep was read from (for messages).
        meta: free-form extras (calibration, transform name, NRRD space, …).
        shear_deg: ``(F,)`` float64, angle (degrees) by which each frame's image axes deviate from
            perpendicular (0 unless a real calibration is a little sheared).
    """

    image_to_world: np.ndarray
    spacing_mm: np.ndarray
    image_size: tuple[int, int]
    images: np.ndarray | None = None
    masks: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    frame_names: list[str] = field(default_factory=list)
    pixel_offset: float = 0.5
    orientation: str = "MF"
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    shear_deg: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.image_to_world = np.asarray(self.image_to_world, dtype=np.float64).reshape(-1, 4, 4)
        n = len(self.image_to_world)
        sp = np.asarray(self.spacing_mm, dtype=np.float64)
        if sp.ndim == 0:
            sp = np.array([sp, sp])
        if sp.shape == (2,):
            sp = np.broadcast_to(sp, (n, 2)).copy()
        if sp.shape != (n, 2):
            raise ValueError(f"spacing_mm must be (2,) or ({n}, 2), got {sp.shape}")
        self.spacing_mm = sp
        shear = np.zeros(n) if self.shear_deg is None else np.asarray(self.shear_deg, np.float64)
        self.shear_deg = np.broadcast_to(shear, (n,)).copy()
        self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        w, h = self.image_size
        for name in ("images", "masks"):
            arr = getattr(self, name)
            if arr is not None:
                arr = np.asarray(arr)
                if name == "masks":
                    arr = arr.astype(bool, copy=False)
                if arr.shape != (n, h, w):
                    raise ValueError(f"{name} must have shape ({n}, {h}, {w}), got {arr.shape}")
                setattr(self, name, arr)
        if self.timestamps is None:
            self.timestamps = np.arange(n, dtype=np.float64)
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(n)
        if not self.frame_names:
            self.frame_names = [f"frame {i}" for i in range(n)]
        if len(self.frame_names) != n:
            raise ValueError(f"frame_names has {len(self.frame_names)} entries for {n} frames")

    # ----------------------------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        """Number of frames ``F``."""
        return len(self.image_to_world)

    @property
    def width(self) -> int:
        """Frame width ``W`` in pixels (number of scan lines)."""
        return self.image_size[0]

    @property
    def height(self) -> int:
        """Frame height ``H`` in pixels (samples along a scan line)."""
        return self.image_size[1]

    def pixel_to_world(self) -> np.ndarray:
        """``(F, 4, 4)`` affine maps from pixel indices ``[c, r, 0, 1]`` to world mm."""
        out = np.empty_like(self.image_to_world)
        for i in range(self.n_frames):
            out[i] = self.image_to_world[i] @ pixel_to_image_matrix(self.spacing_mm[i], self.pixel_offset,
                                                                    self.shear_deg[i])
        return out

    def probe_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-frame world unit vectors ``(lateral, beam, normal)``, each ``(F, 3)``.

        ``lateral`` runs along the image columns (increasing ``c``), ``beam`` down the scan lines
        (increasing ``r``, away from the transducer; off ``lateral``'s perpendicular by the
        shear), ``normal`` is the image plane's unit normal.
        """
        m = self.pixel_to_world()[:, :3, :3]
        lateral = m[:, :, 0] / np.linalg.norm(m[:, :, 0], axis=1, keepdims=True)
        beam = m[:, :, 1] / np.linalg.norm(m[:, :, 1], axis=1, keepdims=True)
        return lateral, beam, self.image_to_world[:, :3, 2].copy()

    def replace(self, **changes: Any) -> "Sweep":
        """A copy with some attributes replaced (arrays are shared, not copied)."""
        return dataclasses.replace(self, **changes)

    def with_masks(self, masks: np.ndarray | None) -> "Sweep":
        """A copy holding ``masks`` ``(F, H, W)`` (anything non-zero is bone)."""
        return self.replace(masks=None if masks is None else np.asarray(masks) != 0)

    def subset(self, indices: Sequence[int] | np.ndarray) -> "Sweep":
        """A sweep of the frames at ``indices`` (in that order)."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        return self.replace(
            image_to_world=self.image_to_world[idx],
            spacing_mm=self.spacing_mm[idx],
            shear_deg=self.shear_deg[idx],
            images=None if self.images is None else self.images[idx],
            masks=None if self.masks is None else self.masks[idx],
            timestamps=self.timestamps[idx],
            frame_names=[self.frame_names[i] for i in idx],
        )

    def __repr__(self) -> str:  # arrays would flood the terminal
        parts = [f"{self.n_frames} frames", f"{self.width}x{self.height} px",
                 f"spacing {self.spacing_mm[0, 0]:.4g}x{self.spacing_mm[0, 1]:.4g} mm"]
        parts.append("images" if self.images is not None else "no images")
        parts.append("masks" if self.masks is not None else "no masks")
        return f"Sweep({', '.join(parts)}, source={self.source!r})"
