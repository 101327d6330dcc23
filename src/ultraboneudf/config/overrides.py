"""Overrides of a :class:`Config`: ``"section.field=value"`` strings (the command line's ``--set``)
or keyword arguments (``iters=1000``, ``train__iters=1000``; a bare field name must be unique across
sections), each value coerced to its field's type; :func:`validate` for the values no run can use;
and :func:`parse_key_values`, the one ``KEY=VALUE`` parser of the command line's options."""

from __future__ import annotations

import json
import math
import types
import typing
from dataclasses import fields
from typing import Any, Iterable, Mapping

from ..errors import InputError
from .introspection import _check_choice, _hints, check_choices, choices
from .sections import Config


def _sections(cfg: Config) -> dict[str, Any]:
    return {f.name: getattr(cfg, f.name) for f in fields(cfg)}


MOVED_KEYS = {
    **{f"model.poisson_{old}": f"poisson.{new}" for old, new in (
        ("depth", "octree_depth"), ("scale", "scale"), ("normals", "normals"), ("orientation", "orientation"),
        ("backend", "backend"), ("threads", "solver_threads"))},
    **{f"train.expand_{name}": f"capudf.expand_{name}" for name in (
        "at", "batch", "candidates", "df_filter", "low_range", "outlier", "rate")},
    "data.capudf_total_queries": "capudf.total_queries", "loss.lambda_scc": "funsr.lambda_scc",
    "loss.lambda_adl": "funsr.lambda_adl", "train.disc_lr": "funsr.disc_lr",
    **{f"extract.{name}": f"grid.{name}" for name in (
        "resolution", "box_margin", "cell_threshold", "udf2sdf", "udf2sdf_project", "far")},
    "extract.grid_box": "grid.box",
    **{f"extract.clean_{name}": f"clean.{name}" for name in (
        "crossing", "vertex", "qef_window", "project_steps", "merge")},
}
"""Keys of earlier versions that a method's or an extractor's own section now holds: old → new."""


def _resolve_key(cfg: Config, key: str) -> tuple[Any, str]:
    key = key.replace("__", ".")
    if key in MOVED_KEYS:
        raise InputError(f"config key {key!r} is now {MOVED_KEYS[key]!r}")
    sections = _sections(cfg)
    if "." in key:
        section, name = key.split(".", 1)
        if section not in sections:
            raise InputError(f"unknown config section {section!r} in {key!r}; "
                             f"sections: {', '.join(sections)}")
        obj = sections[section]
        if name not in {f.name for f in fields(obj)}:
            raise InputError(f"unknown config key {key!r}")
        return obj, name
    owners = [obj for obj in sections.values() if key in {f.name for f in fields(obj)}]
    if len(owners) != 1:
        what = "ambiguous" if owners else "unknown"
        raise InputError(f"{what} config key {key!r}; write it as section.{key}")
    return owners[0], key


def _optional(hint: Any) -> Any:
    """``X`` for a hint ``X | None`` (``Optional[X]``), else ``None``."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and len(args) == 2 and type(None) in args:
        return next(a for a in args if a is not type(None))
    return None


def _expected(hint: Any) -> str:
    """How a value of type ``hint`` is written on the command line (for error messages)."""
    if _optional(hint) is not None:
        return _expected(_optional(hint)) + " or none"
    if typing.get_origin(hint) is tuple:
        inner = typing.get_args(hint)[0]
        return "comma-separated " + ("integers" if inner is int else "numbers")
    return {bool: "true or false", int: "an integer", float: "a number"}.get(hint, "a string")


def coerce(hint: Any, value: Any, key: str, what: str = "config key") -> Any:
    """Convert ``value`` (possibly a string from the command line) to the type ``hint`` of a
    dataclass field (``bool``, ``int``, ``float``, ``str``, ``tuple[...]``, or one of them ``| None``,
    written ``none``); :class:`InputError` naming the ``what`` ``key`` and the expected type otherwise."""
    if _optional(hint) is not None:
        if value is None or (isinstance(value, str) and value.strip().lower() in ("none", "null")):
            return None
        return coerce(_optional(hint), value, key, what)
    given = value
    try:
        if typing.get_origin(hint) is tuple:
            if isinstance(value, str):
                value = json.loads("[" + value.strip("()[] ") + "]")
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ValueError(value)
            inner = typing.get_args(hint)[0]
            return tuple(coerce(inner, v, key, what) for v in value)
        if hint is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                if low not in {"true", "false", "1", "0", "yes", "no"}:
                    raise ValueError(value)
                return low in {"true", "1", "yes"}
            if not isinstance(value, bool):
                raise ValueError(value)
            return value
        if hint in (int, float):
            if isinstance(value, str):
                value = json.loads(value)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(value)
            if hint is int:
                if float(value) != int(value):
                    raise ValueError(value)
                return int(value)
            return float(value)
        if not isinstance(value, str):
            raise ValueError(value)
        return value
    except (ValueError, TypeError, OverflowError, json.JSONDecodeError):
        raise InputError(f"bad value {given!r} for {what} {key!r} (expected {_expected(hint)})") from None


def set_value(cfg: Config, key: str, value: Any) -> None:
    """Set the field ``key`` (``section.name``, ``section__name`` or a name only one section has) of
    ``cfg`` to ``value`` coerced to its type; :class:`InputError` naming the key and the problem."""
    obj, name = _resolve_key(cfg, key)
    hint = _hints(type(obj))[name]
    value = coerce(str if choices(obj, name) else hint, value, key)
    _check_choice(obj, name, value)
    setattr(obj, name, value)


MAX_DEPTH = 11
"""Deepest octree a run may ask for (2,048 leaves per axis; depth 12 exceeds a workstation's memory)."""


def validate(cfg: Config, trains: bool = True) -> Config:
    """Raise :class:`InputError` for values no run can use (named by their ``--set`` spelling);
    returns ``cfg``. ``trains``: the method trains a network (Poisson does not, and sets no
    iterations)."""
    problems = []

    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            section, name = key.split(".")
            problems.append(f"{key}={getattr(getattr(cfg, section), name)!r} ({what})")

    for section in _sections(cfg).values():
        check_choices(section)
        for f in fields(section):
            value = getattr(section, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                problems.append(f"{section.SECTION}.{f.name}={value!r} (a finite number)")
    t, d, e, lo = cfg.train, cfg.data, cfg.extract, cfg.loss
    need(t.iters >= (1 if trains else 0), "train.iters", "at least 1")
    need(t.batch >= 1, "train.batch", "at least 1")
    need(math.isfinite(t.lr) and 0 < t.lr <= 1, "train.lr", "a learning rate in (0, 1]")
    need(t.warmup >= 0, "train.warmup", "0 or more")
    need(0.0 <= lo.warm_start < 1.0, "loss.warm_start", "a fraction in [0, 1)")
    need(1 <= e.max_depth <= MAX_DEPTH, "extract.max_depth", f"between 1 and {MAX_DEPTH}")
    need(cfg.grid.resolution >= 2, "grid.resolution", "at least 2")
    for key in ("data.voxel_size_mm", "data.surface_fit_mm", "data.bridge", "data.frame_bridge", "data.rim_reach",
                "data.shadow_mm", "data.outlier_sigmas", "extract.trim_mm", "extract.trim_normal_mm",
                "extract.trim_normal_sigmas", "extract.trim_rim_mm", "extract.fit_mm", "extract.min_leaf_mm"):
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        need(math.isfinite(value) and value >= 0, key, "finite and 0 or more")
    for name in ("trim_normal_mm", "trim_rim_mm"):
        if getattr(e, name) > 0 and d.surface_fit_mm <= 0:
            problems.append(f"extract.{name} needs the local planes: set data.surface_fit_mm > 0")
    need(0 <= e.trim_grazing_deg < 90, "extract.trim_grazing_deg", "0 (off) or an angle under 90 degrees")
    need(d.denoise >= 0, "data.denoise", "0 or more passes")
    need(d.surface_fit_points >= 0, "data.surface_fit_points", "0 (the radius as given) or more")
    need(d.steep_planes_deg == 0 or 60 < d.steep_planes_deg < 90, "data.steep_planes_deg",
         "0 (none) or an angle between 60 and 90 degrees")
    need(d.max_voxels >= 0, "data.max_voxels", "0 (no limit) or more")
    need(lo.gs_anchors >= 0, "loss.gs_anchors", "0 (all) or more")
    need(lo.os_rows >= 0, "loss.os_rows", "0 (all) or more")
    if problems:
        raise InputError("bad configuration: " + "; ".join(problems))
    return cfg


def apply_overrides(cfg: Config, overrides: Mapping[str, Any] | None = None,
                    assignments: list[str] | tuple[str, ...] = ()) -> Config:
    """Apply keyword overrides and ``key=value`` strings to ``cfg`` in place; returns ``cfg``."""
    for key, value in (overrides or {}).items():
        set_value(cfg, key, value)
    for item in assignments:  # one at a time: a key may be spelled two ways, the last one given wins
        for key, value in parse_key_values([item], "--set").items():
            try:
                set_value(cfg, key, value)
            except InputError as exc:
                raise InputError(f"--set {item!r}: {exc}") from None
    return cfg


def parse_key_values(items: Iterable[str], option: str, types: Mapping[str, Any] | None = None,
                     what: str = "key") -> dict[str, Any]:
    """``KEY=VALUE`` strings (a repeatable command-line ``option``) → ``{KEY: VALUE}``, the last
    of a key given winning. With ``types`` (``{key: type hint}``) every key must be one of them and
    every value is coerced to its type (:func:`coerce`: numbers, ``a,b,c`` tuples, ``none``);
    without, the values stay strings. A bad item raises :class:`InputError`, one line: the option,
    the item, then the problem with its key (``expected KEY=VALUE``, ``unknown <what> 'k'``, ``bad
    value 'v' for <what> 'k' (expected …)``)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key:
            raise InputError(f"{option} {item!r}: expected KEY=VALUE")
        if types is not None:
            if key not in types:
                raise InputError(f"{option} {item!r}: unknown {what} {key!r}; {what}s: {', '.join(sorted(types))}")
            try:
                value = coerce(types[key], value, key, what)
            except InputError as exc:
                raise InputError(f"{option} {item!r}: {exc}") from None
        out[key] = value
    return out
