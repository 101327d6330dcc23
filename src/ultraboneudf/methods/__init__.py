"""Reconstruction methods by name. Adding a method = one module + one entry in :func:`_registry`
(and its name in :data:`NAMES`).

Each entry is a :class:`~ultraboneudf.methods.base.Method`: ``fit`` and ``configure(cfg)``,
which sets the method's own defaults on a fresh preset before the user's overrides. The method
modules (and PyTorch) are imported when the registry :data:`METHODS` is first used; :data:`NAMES`
is there without them, for the command line's choices.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from ..errors import InputError
from .base import FitFunction, Fitted, Method

NAMES = ("ultraboneudf", "capudf", "funsr", "carotidudf", "poisson", "vanilla_udf", "ultraboneudf_pull")
"""The registered method names, in the order of :data:`METHODS`."""


@cache
def _registry() -> dict[str, Method]:
    from . import capudf, carotidudf, funsr, poisson, ultraboneudf

    return {
        "ultraboneudf": Method(ultraboneudf.fit, summary="tangent loss + L_GS, DualMesh-UDF (§1)",
                               takes_planes=True, takes_checkpoint=True),
        "capudf": Method(capudf.fit, capudf.configure, "CAP-UDF: consistency-aware loss, two stages (§3)",
                         takes_checkpoint=True),
        "funsr": Method(funsr.fit, funsr.configure, "FUNSR: SDF + SCC + adversarial loss, marching cubes (§4)",
                        takes_planes=True),
        "carotidudf": Method(carotidudf.fit, carotidudf.configure_carotidudf, "CarotidUDF as inferred (§5)",
                             takes_planes=True, takes_checkpoint=True),
        "poisson": Method(poisson.fit, poisson.configure, "screened Poisson, depth 9 (§7); extra [poisson]",
                          takes_probe=True, trains=False),
        "vanilla_udf": Method(carotidudf.fit, carotidudf.configure_vanilla, "ablation: L_pull + UDF→SDF (§5.5)",
                              takes_planes=True, takes_checkpoint=True),
        "ultraboneudf_pull": Method(carotidudf.fit, carotidudf.configure_pull,
                                    "ablation: L_pull + DualMesh-UDF (§5.5)", takes_planes=True,
                                    takes_checkpoint=True),
    }


def __getattr__(name: str) -> Any:
    if name == "METHODS":
        return _registry()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def get_method(name: str) -> Method:
    """The registry entry of a method; unknown names raise :class:`InputError`."""
    try:
        return _registry()[name]
    except KeyError:
        raise InputError(f"unknown method {name!r}; choose one of {', '.join(NAMES)}") from None


__all__ = ["METHODS", "NAMES", "get_method", "Fitted", "Method", "FitFunction"]
