"""Reconstruction methods by name. Adding a method = one module + one line in :data:`METHODS`.

Each entry is a :class:`~ultraboneudf.methods.base.Method`: ``fit`` and ``configure(cfg, preset)``,
which sets the method's own defaults on a fresh preset before the user's overrides.
"""

from __future__ import annotations

from ..errors import InputError
from . import capudf, carotidudf, funsr, poisson, ultraboneudf
from .base import FitFunction, Fitted, Method

METHODS: dict[str, Method] = {
    "ultraboneudf": Method(ultraboneudf.fit, summary="tangent loss + L_GS, DualMesh-UDF (§1)",
                           takes_planes=True),
    "capudf": Method(capudf.fit, capudf.configure, "CAP-UDF: consistency-aware loss, two stages (§3)"),
    "funsr": Method(funsr.fit, funsr.configure, "FUNSR: SDF + SCC + adversarial loss, marching cubes (§4)",
                    takes_planes=True),
    "carotidudf": Method(carotidudf.fit, carotidudf.configure_carotidudf, "CarotidUDF as inferred (§5)",
                         takes_planes=True),
    "poisson": Method(poisson.fit, poisson.configure, "screened Poisson, depth 9 (§7); extra [poisson]",
                      takes_probe=True),
    "vanilla_udf": Method(carotidudf.fit, carotidudf.configure_vanilla, "ablation: L_pull + UDF→SDF (§5.5)",
                          takes_planes=True),
    "ultraboneudf_pull": Method(carotidudf.fit, carotidudf.configure_pull,
                                "ablation: L_pull + DualMesh-UDF (§5.5)", takes_planes=True),
}


def get_method(name: str) -> Method:
    """The registry entry of a method; unknown names raise :class:`InputError`."""
    try:
        return METHODS[name]
    except KeyError:
        raise InputError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}") from None


__all__ = ["METHODS", "get_method", "Fitted", "Method", "FitFunction"]
