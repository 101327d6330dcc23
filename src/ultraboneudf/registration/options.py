"""The settings of a registration, with their defaults. Lengths are in mm; ``None`` means "from the
CT bone's size" (see :meth:`RegisterOptions.resolve`)."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class RegisterOptions:
    """How :func:`~ultraboneudf.registration.register` searches and refines (mm)."""

    grid_mm: float | None = None
    """Step of the CT's distance grid (default: the bone's bounding-box diagonal / 150, within 1–3)."""
    voxel_mm: float | None = None
    """The target is thinned to one point per cell of this edge (default: 0.75 × grid_mm, within 1–2)."""
    normal_radius_mm: float | None = None
    """Radius of the neighbourhood that fits the plane at each target point (default: max(4, 3 × voxel_mm))."""
    anchors: int = 6
    """Target points that anchor pose hypotheses (spread over the cloud; more: more robust, slower)."""
    turns: int = 36
    """Turns about the normal per anchor and CT point (36: every 10°)."""
    ct_spacing_mm: float | None = None
    """Spacing of the CT points an anchor may land on (default: the diagonal / 50, within 2–8)."""
    search_tau_mm: float | None = None
    """Distance from which a point counts as unexplained in the search (default: max(2 × ct_spacing_mm, 3 × grid_mm))."""
    first_points: int = 32
    """Target points that score every hypothesis in the first pass."""
    second_points: int = 128
    """Target points that score the first pass's best again."""
    keep: int = 400
    """Hypotheses kept after the second pass."""
    candidates: int = 40
    """Distinct poses refined in the distance field."""
    refine_points: int = 400
    """Target points in the distance-field refinement."""
    quick_points: int = 2000
    """Target points in the ICP of each finalist (the poses are ranked on these)."""
    icp_points: int = 20000
    """At most this many target points in the last ICP of the chosen pose."""
    icp_cutoffs_mm: tuple[float, ...] = (6.0, 4.0, 3.0)
    """Tukey cut-offs of the final ICP, widest first; a point farther than the last one does not count."""
    icp_iterations: int = 30
    """Largest number of ICP iterations."""
    finalists: int = 3
    """Distinct poses taken through ICP; the best is the answer, the best of the others far enough from it the runner-up."""
    inlier_mm: float = 2.0
    """A target point within this distance of the placed CT is explained (overlap, residual, scores)."""
    separation_mm: float = 4.0
    """A runner-up pose moves the CT surface by more than this (mean) from the answer."""

    def resolve(self, diagonal: float) -> "RegisterOptions":
        """A copy with every ``None`` length set from the CT's bounding-box diagonal (mm)."""
        from .model import grid_spacing

        grid = self.grid_mm or grid_spacing(diagonal)
        voxel = self.voxel_mm or float(np.clip(0.75 * grid, 1.0, 2.0))
        radius = self.normal_radius_mm or max(4.0, 3.0 * voxel)
        spacing = self.ct_spacing_mm or float(np.clip(diagonal / 50.0, 2.0, 8.0))
        tau = self.search_tau_mm or max(2.0 * spacing, 3.0 * grid)
        return dataclasses.replace(self, grid_mm=round(grid, 4), voxel_mm=round(voxel, 4),
                                   normal_radius_mm=round(radius, 4), ct_spacing_mm=round(spacing, 4),
                                   search_tau_mm=round(tau, 4))

    def to_dict(self) -> dict[str, Any]:
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v) for f in fields(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "RegisterOptions":
        """Options from a mapping (e.g. a registration's JSON ``options``); unknown keys and values
        of the wrong kind are an :class:`InputError`."""
        return with_overrides(cls(), values)


def with_overrides(options: RegisterOptions, values: dict[str, Any]) -> RegisterOptions:
    """``options`` with ``values`` (name → value; strings are parsed) replacing fields, checked:
    counts are positive integers, lengths positive numbers."""
    hints = typing.get_type_hints(RegisterOptions)
    out = {}
    for key, value in values.items():
        if key not in hints:
            raise InputError(f"unknown registration option {key!r}; options: {', '.join(hints)}")
        out[key] = _coerce(key, hints[key], value)
    return dataclasses.replace(options, **out)


def _coerce(key: str, hint: Any, value: Any) -> Any:
    kind = hint
    if typing.get_origin(hint) is not tuple:
        kind = next((a for a in typing.get_args(hint) if a is not type(None)), hint)
    try:
        if value is None or (isinstance(value, str) and value.strip().lower() == "none"):
            if type(None) not in typing.get_args(hint):
                raise ValueError("cannot be none")
            return None
        if typing.get_origin(kind) is tuple:
            items = value.split(",") if isinstance(value, str) else list(value)
            result = tuple(float(v) for v in items)
            if not result or min(result) <= 0:
                raise ValueError("must be positive numbers")
            return result
        if kind is int:
            number = float(value)
            if number != int(number) or number < 1:
                raise ValueError("must be a whole number ≥ 1")
            return int(number)
        number = float(value)
        if not np.isfinite(number) or number <= 0:
            raise ValueError("must be a positive number of mm")
        return number
    except (TypeError, ValueError) as exc:
        raise InputError(f"registration option {key}={value!r}: {exc}") from None
