"""What every method returns, and the signature it implements.

A method is ``fit(points, config, device, seed, progress) -> Fitted`` where ``points`` is the
pre-processed cloud in *unit space* (``(N, 3)`` float64, see :class:`~ultraboneudf.geometry.Normalizer`).
It returns a field for the extractor, or a unit-space mesh directly (e.g. Poisson).
"""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Callable

import numpy as np
import torch
import trimesh

from ..config import Config
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


FitFunction = Callable[[np.ndarray, Config, torch.device, int, Progress], Fitted]
