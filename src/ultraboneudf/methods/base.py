"""What every method returns, and the signature it implements.

A method is ``fit(points, config, device, seed, progress) -> Fitted`` where ``points`` is the
pre-processed cloud in *unit space* (``(N, 3)`` float64, see :class:`~ultraboneudf.geometry.Normalizer`).
It returns a field for the extractor, or a unit-space mesh directly (e.g. Poisson).

A method whose registry entry has ``takes_probe=True`` also accepts ``probe=`` (``(N, 3)`` unit
space, row ``i`` the probe position of ``points[i]``, or ``None``): per-point provenance from a
tracked sweep (§7.2 alternative B). One with ``takes_planes=True`` accepts ``planes=``: the
pipeline's :class:`~ultraboneudf.geometry.surface_fit.LocalPlanes` of ``points`` (lengths in unit
space), or ``None`` when ``data.surface_fit_mm`` is 0. Other methods never receive them.

The registry (:data:`ultraboneudf.methods.METHODS`) holds one :class:`Method` per name: its ``fit``
and a ``configure(cfg)`` that sets the method's own defaults (network, loss, schedule,
extractor) on a fresh preset config *before* the user's overrides are applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import TYPE_CHECKING, Any, Callable

from ..config import Config

if TYPE_CHECKING:  # the registry is read by the command line before PyTorch is needed
    import numpy as np
    import torch
    import trimesh

    from ..fields.base import Field
    from ..progress import Progress


@dataclass
class Fitted:
    """A method's result in unit space."""

    field: Field | None = None
    mesh: trimesh.Trimesh | None = None
    counts: dict[str, int] = dc_field(default_factory=dict)
    timings: dict[str, float] = dc_field(default_factory=dict)  # preprocess_s, train_s
    history: dict[str, list[float]] = dc_field(default_factory=dict)
    surface: np.ndarray | None = None
    """Unit-space surface points (N, 3) for extractors that need them (CAP-UDF box, UDF→SDF signs)."""
    normals: np.ndarray | None = None
    """Oriented unit normals (N, 3) of ``surface`` (CarotidUDF ``normal-sign`` conversion)."""
    info: dict[str, Any] = dc_field(default_factory=dict)
    """Choices the method resolved at run time (e.g. ``poisson_orientation``), for the sidecar."""


FitFunction = Callable[["np.ndarray", Config, "torch.device", int, "Progress"], Fitted]
ConfigureFunction = Callable[[Config], None]


def keep_preset(cfg: Config) -> None:
    """``configure`` of a method whose defaults are the presets themselves (UltraBoneUDF)."""


@dataclass(frozen=True)
class Method:
    """A registry entry: ``fit`` and ``configure(cfg)`` (method defaults, in place).
    ``takes_probe`` / ``takes_planes``: ``fit`` accepts per-point probe positions as ``probe=`` /
    the local planes as ``planes=`` (see the module doc); ``takes_checkpoint``: ``fit`` accepts a
    :class:`~ultraboneudf.checkpoints.Checkpoint` as ``checkpoint=`` (its training can resume)."""

    fit: FitFunction
    configure: ConfigureFunction = keep_preset
    summary: str = ""
    takes_probe: bool = False
    takes_planes: bool = False
    takes_checkpoint: bool = False
    trains: bool = True
    """``fit`` trains a network for ``train.iters`` steps (Poisson solves one linear system)."""
