"""Reconstruction methods by name. Adding a method = one module + one line in :data:`METHODS`."""

from __future__ import annotations

from ..errors import InputError
from . import ultraboneudf
from .base import FitFunction, Fitted

METHODS: dict[str, FitFunction] = {
    "ultraboneudf": ultraboneudf.fit,
}


def get_method(name: str) -> FitFunction:
    """The ``fit`` function of a method; unknown names raise :class:`InputError`."""
    try:
        return METHODS[name]
    except KeyError:
        raise InputError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}") from None


__all__ = ["METHODS", "get_method", "Fitted"]
