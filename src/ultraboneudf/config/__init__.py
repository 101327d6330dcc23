"""Typed configuration of a reconstruction, the named presets, and overrides.

A :class:`Config` has one dataclass per stage (:mod:`.sections`). Every field carries the paper's or
the official code's value (see ``docs/ALGORITHMS.md``); the presets (:mod:`.presets`) differ only
where the two disagree (§1.11) and in the ``fast`` and ``robust`` presets designed here. Thresholds
of the field and of the extractor are in *unit space* (the normalised frame of §0.1); quantities in
millimetres say ``_mm`` in their name.

Overrides (:mod:`.overrides`) are ``"section.field=value"`` strings (the CLI's ``--set``) or keyword
arguments (``iters=1000``, ``train__iters=1000``); a bare field name must be unique across sections.
What the sections say about their fields (documentation, modes) is in :mod:`.introspection`.
"""

from __future__ import annotations

from .introspection import check_choices, choices, field_docs
from .overrides import (MAX_DEPTH, MOVED_KEYS, apply_overrides, coerce, parse_key_values, set_value,
                        validate)
from .presets import DEFAULT_PRESET, DMU_DEFAULTS, PRESET_HELP, PRESETS, preset
from .sections import (DEPTH_WIDTHS, GPU_BATCH_FACTOR, GPU_LR_FACTOR, GPU_STEP_DIVISOR, GS_FORMS, CapudfConfig,
                       CleanConfig, Config, DataConfig, ExtractConfig, FunsrConfig, GridConfig, LossConfig,
                       ModelConfig, PoissonConfig, TrainConfig, model_widths, resolve_budget, training_schedule)

UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 0.001}
"""Millimetres per unit of the units a point cloud file may be given in (``reconstruct --units``)."""

__all__ = [
    "CapudfConfig", "CleanConfig", "Config", "DataConfig", "DEFAULT_PRESET", "DEPTH_WIDTHS", "DMU_DEFAULTS",
    "ExtractConfig", "FunsrConfig", "GPU_BATCH_FACTOR", "GPU_LR_FACTOR", "GPU_STEP_DIVISOR", "GS_FORMS",
    "GridConfig", "LossConfig", "MAX_DEPTH", "MOVED_KEYS", "ModelConfig", "PRESETS", "PRESET_HELP",
    "PoissonConfig", "TrainConfig", "UNITS_MM", "apply_overrides", "check_choices", "choices", "coerce",
    "field_docs", "model_widths", "parse_key_values", "preset", "resolve_budget", "set_value",
    "training_schedule", "validate",
]
