"""The simulator's parameters and named noise levels (no heavy imports: the command line's help
lists them). :mod:`ultraboneudf.synth.simulator` runs the simulation."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from ..errors import InputError


@dataclass
class SimulationConfig:
    """Parameters of :func:`simulate_sweep` (lengths in mm, angles in degrees)."""

    width_px: int = 256
    """Image width (scan lines)."""
    height_px: int = 320
    """Image height (samples per scan line)."""
    spacing_mm: float = 0.15
    """Pixel size, both directions."""
    frame_spacing_mm: float = 0.8
    """Mean distance between frames along the sweep (ignored when ``n_frames`` is set)."""
    n_frames: int | None = None
    """Number of frames (default: from the sweep length and ``frame_spacing_mm``)."""
    sweep_length_mm: float | None = None
    """Length of the sweep (default: the bone's extent along the sweep axis − 2 ``margin_mm``)."""
    margin_mm: float = 5.0
    """Distance kept from the bone's ends."""
    sweep_axis: tuple[float, float, float] | None = None
    """Direction of the sweep (default: the mesh's longest principal axis)."""
    view: tuple[float, float, float] | None = None
    """Direction from the bone to the probe (default: the smallest principal axis)."""
    tissue_depth_mm: float = 10.0
    """Soft tissue between the probe face and the highest bone point in view."""
    speed_variation: float = 0.3
    """Relative amplitude of the (smooth) speed changes along the sweep."""
    tilt_deg: float = 8.0
    """Amplitude of the slow tilt of the image plane about the lateral axis."""
    rock_deg: float = 4.0
    """Amplitude of the slow in-plane rotation."""
    jitter_mm: float = 0.3
    """Hand jitter, translation (per axis, smooth over a few frames)."""
    jitter_deg: float = 0.5
    """Hand jitter, rotation (per axis)."""
    tracking_noise_mm: float = 0.1
    """Tracking error of the recorded poses, translation (per axis, independent per frame)."""
    tracking_noise_deg: float = 0.1
    """Tracking error of the recorded poses, rotation (per axis, about the probe face centre)."""
    frame_rate_hz: float = 30.0
    """Frames per second (timestamps in ms)."""
    max_incidence_deg: float = 75.0
    """Surfaces hit more obliquely return no echo and are not visible truth."""
    speckle_axial_mm: float = 0.12
    """Speckle correlation length along the beam."""
    speckle_lateral_mm: float = 0.3
    """Speckle correlation length across the beams."""
    n_fascia: int = 3
    """Bright soft-tissue lines (no shadow) per image."""
    shadow_level: float = 0.06
    """Brightness under the bone relative to tissue."""
    pred_gap_fraction: float = 0.1
    """Fraction of visible columns missing from the predicted mask (in runs)."""
    pred_gap_mean_mm: float = 2.0
    """Mean length of a gap."""
    pred_max_incidence_deg: float = 60.0
    """Echoes more oblique than this fade out of the predicted mask (all gone at
    ``max_incidence_deg``)."""
    pred_jitter_px: float = 1.0
    """Boundary jitter of the predicted mask (std, pixels, smooth along the frame)."""
    pred_bias_px: float = 0.5
    """Per-frame offset of the predicted boundary (std, pixels)."""
    pred_thickness_px: int = 3
    """Thickness of the predicted mask band."""
    pred_fp_per_frame: float = 0.3
    """Mean number of off-surface false-positive segments per frame."""
    pred_beam_noise_mm: float = 0.0
    """Independent noise (std, mm) of the predicted boundary along the beam, per scan line."""
    pred_fp_fraction: float = 0.0
    """Fraction of the predicted scan lines whose bone pixel is a false echo in the shadow
    instead: the true surface is missed there and a pixel lies ``U(0, pred_fp_depth_mm)`` deeper."""
    pred_fp_depth_mm: float = 10.0
    """How far under the surface the scattered false echoes of ``pred_fp_fraction`` reach."""
    pred_offset_mm: float = 0.0
    """Amplitude (std, mm) of an offset of the predicted boundary along the beam that drifts slowly
    along the sweep (a segmentation that takes the band's top or bottom, a calibration error)."""
    pred_oblique_mm: float = 0.0
    """How far (mm) the predicted boundary of a face lies out of the bone, along its normal, as that
    face turns away from the beam: ``pred_oblique_mm × (1 − cos incidence)`` (0.5 mm at 50°, 1.2 mm
    at 80° with 1.5 mm). Beams are wider than they are long, so an oblique echo is smeared across the
    face, and a segmentation puts the boundary at the outer edge of the smear; real clouds and
    sweeps show it against their CT (docs/real_data.md)."""
    pred_sheets_per_cm: float = 0.0
    """Mean number, per 10 mm of sweep, of false-echo sheets in front of the bone: a fascia line (or,
    without one, a smooth layer 3–15 mm above the bone) taken for bone over a patch 4–20 mm wide
    for 5–25 mm of the sweep."""
    pred_streaks_per_frame: float = 0.0
    """Mean number of streaks per frame: a run of one to three scan lines labelled from the bone up
    toward the probe, 3–20 mm long."""
    pred_below_per_cm: float = 0.0
    """Mean number, per 10 mm of sweep, of echo clusters under the bone (reverberation): the bone
    line copied 2–6 mm deeper over a patch 3–12 mm wide for 3–10 mm of the sweep."""
    missing_runs: int = 0
    """Runs of consecutive frames missing from the recording (probe lifted, tracking lost); the
    visible truth still covers them, so a reconstruction must bridge them."""
    missing_run_mm: float = 4.0
    """Length of each missing run along the sweep."""
    gt_step_mm: float = 0.25
    """Largest spacing of the visible-truth pass's beams, across the image and along the sweep
    (poses interpolated between frames); on a mesh with fine faces the beams are spaced a sixth of
    its median edge instead (:func:`~ultraboneudf.synth.visible_truth.truth_beam_spacing`)."""
    seed: int = 0
    """Random seed: the same mesh, config and seed give the same sweep."""

    def __post_init__(self) -> None:
        problems = [f"{name}={getattr(self, name)!r} ({what})" for name, what in _problems(self)]
        if problems:
            raise InputError("impossible simulator settings: " + "; ".join(problems))

    def replace(self, **changes: Any) -> "SimulationConfig":
        return dataclasses.replace(self, **changes)


MAX_IMAGE_PX = 4096
"""Largest simulated image side, in pixels."""


def _problems(cfg: SimulationConfig) -> list[tuple[str, str]]:
    """``(field, what it must be)`` for every value no simulation can use."""
    out = []

    def need(ok: bool, name: str, what: str) -> None:
        if not ok:
            out.append((name, what))

    def number(value: Any) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if value is not None and not isinstance(value, tuple) and not number(value):
            out.append((f.name, "a finite number"))
    if out:
        return out
    for name in ("width_px", "height_px"):
        need(16 <= getattr(cfg, name) <= MAX_IMAGE_PX, name, f"between 16 and {MAX_IMAGE_PX} pixels")
    for name in ("spacing_mm", "frame_spacing_mm", "frame_rate_hz", "speckle_axial_mm", "speckle_lateral_mm",
                 "pred_gap_mean_mm", "gt_step_mm"):
        need(getattr(cfg, name) > 0, name, "more than 0")
    for name in ("margin_mm", "tissue_depth_mm", "jitter_mm", "tracking_noise_mm", "pred_jitter_px",
                 "pred_bias_px", "pred_fp_per_frame", "pred_beam_noise_mm", "pred_fp_depth_mm",
                 "missing_run_mm", "n_fascia", "missing_runs", "seed", "pred_offset_mm", "pred_sheets_per_cm",
                 "pred_streaks_per_frame", "pred_below_per_cm", "pred_oblique_mm"):
        need(getattr(cfg, name) >= 0, name, "0 or more")
    for name in ("tilt_deg", "rock_deg", "jitter_deg", "tracking_noise_deg"):
        need(0 <= getattr(cfg, name) < 90, name, "an angle from 0 to under 90 degrees")
    for name in ("max_incidence_deg", "pred_max_incidence_deg"):
        need(0 < getattr(cfg, name) <= 90, name, "an angle above 0 and up to 90 degrees")
    for name in ("speed_variation", "pred_gap_fraction"):
        need(0 <= getattr(cfg, name) < 1, name, "a fraction from 0 to under 1")
    for name in ("shadow_level", "pred_fp_fraction"):
        need(0 <= getattr(cfg, name) <= 1, name, "a fraction from 0 to 1")
    need(cfg.pred_thickness_px >= 1, "pred_thickness_px", "1 or more pixels")
    need(cfg.n_frames is None or 2 <= cfg.n_frames <= 100_000, "n_frames", "none, or 2 to 100,000 frames")
    need(cfg.sweep_length_mm is None or cfg.sweep_length_mm > 0, "sweep_length_mm", "none, or more than 0")
    for name in ("sweep_axis", "view"):
        v = getattr(cfg, name)
        need(v is None or (len(v) == 3 and all(number(x) for x in v) and any(x != 0 for x in v)), name,
             "none, or a direction of three numbers, not all 0")
    for name in ("width_px", "height_px", "n_fascia", "missing_runs", "pred_thickness_px", "seed"):
        need(isinstance(getattr(cfg, name), int), name, "a whole number")
    need(cfg.n_frames is None or isinstance(cfg.n_frames, int), "n_frames", "a whole number")
    return out


NOISE_PRESETS: dict[str, dict[str, float]] = {
    "none": dict(speed_variation=0.0, tilt_deg=0.0, rock_deg=0.0, jitter_mm=0.0, jitter_deg=0.0,
                 tracking_noise_mm=0.0, tracking_noise_deg=0.0, pred_gap_fraction=0.0,
                 pred_jitter_px=0.0, pred_bias_px=0.0, pred_fp_per_frame=0.0,
                 pred_max_incidence_deg=75.0),
    "default": {},
    "high": dict(speed_variation=0.5, tilt_deg=12.0, rock_deg=8.0, jitter_mm=0.6, jitter_deg=1.0,
                 tracking_noise_mm=0.3, tracking_noise_deg=0.3, pred_gap_fraction=0.25,
                 pred_jitter_px=2.0, pred_bias_px=1.0, pred_fp_per_frame=1.0),
    "moderate": dict(pred_beam_noise_mm=0.3, frame_spacing_mm=0.5),
    "hard": dict(pred_beam_noise_mm=0.8, pred_fp_fraction=0.03, pred_fp_depth_mm=10.0,
                 frame_spacing_mm=1.5, missing_runs=3, missing_run_mm=4.0,
                 tracking_noise_mm=0.3, tracking_noise_deg=0.3),
    "real": dict(pred_beam_noise_mm=1.0, pred_fp_fraction=0.01, pred_fp_depth_mm=10.0,
                 frame_spacing_mm=1.0, speed_variation=0.6, missing_runs=2, missing_run_mm=4.0,
                 tracking_noise_mm=0.3, tracking_noise_deg=0.3, pred_offset_mm=1.0, pred_oblique_mm=1.5,
                 pred_sheets_per_cm=0.35, pred_streaks_per_frame=0.4, pred_below_per_cm=0.2),
}
"""Named noise levels for ``simulate --noise``: ``none`` (ideal sweep and masks), ``default``,
``high`` (a shaky hand, poor masks), and the robustness benchmark's ``moderate`` (0.3 mm noise along
the beam, frames every 0.5 mm) and ``hard`` (0.8 mm noise along the beam, 3% of the scan lines a
false echo up to 10 mm under the surface, frames every 1.5 mm with three 4 mm runs missing,
tracking error 0.3 mm / 0.3° per frame), and ``real``, the false echoes of real segmentations
(docs/real_data.md): 1 mm noise along the beam and an offset along it drifting by 1 mm along the
sweep, oblique faces' boundary up to 1.1 mm out of the bone, frames every 1 mm at a varying
pace, two runs of lost frames, fascia sheets taken for bone in front of it, streaks rising from it
toward the probe and reverberation clusters under it; each on top of ``default``'s segmentation
errors."""


def config_with_noise(noise: str = "default", **overrides: Any) -> SimulationConfig:
    """A :class:`SimulationConfig` at a named noise level, with field overrides."""
    if noise not in NOISE_PRESETS:
        raise InputError(f"unknown noise level {noise!r}; choose from {', '.join(NOISE_PRESETS)}")
    names = {f.name for f in dataclasses.fields(SimulationConfig)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise InputError(f"unknown simulation option(s) {', '.join(unknown)}")
    return SimulationConfig(**{**NOISE_PRESETS[noise], **overrides})
