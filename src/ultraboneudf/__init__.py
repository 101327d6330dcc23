"""ultraboneudf: bone surface meshes (mm) from tracked ultrasound point clouds.

>>> import ultraboneudf
>>> points = ultraboneudf.load_points("scan.xyz")                  # (N, 3) mm
>>> rec = ultraboneudf.reconstruct(points)                        # doctest: +SKIP
>>> rec.save("bone.ply")                                         # mesh + bone.ply.json sidecar
>>> sp = ultraboneudf.sweep_points("sweep_dir")                  # doctest: +SKIP
>>> rec = ultraboneudf.reconstruct(sp.points, probe_positions=sp.probe_position,
...                                frame_index=sp.frame_index)   # doctest: +SKIP

Section numbers (``§1.6``) in docstrings refer to ``docs/ALGORITHMS.md``, the specification.

The names below are imported on first use, so that ``import ultraboneudf`` (and the command
line's ``--help``) does not load PyTorch.
"""

from __future__ import annotations


from ._lazy import lazy_getattr
from ._version import __version__

_WHERE = {
    "Config": "config", "preset": "config", "InputError": "errors",
    "EvalResult": "evaluation", "evaluate": "evaluation",
    "load_mesh": "io", "load_points": "io", "save_mesh": "io",
    "Reconstruction": "pipeline", "reconstruct": "pipeline", "reconstruct_many": "pipeline",
    "FittedSurface": "pipeline", "fit": "pipeline", "configure": "pipeline", "FitIssue": "pipeline",
    "Registration": "registration", "register": "registration",
    "SweepOptions": "sweep.front_end", "SweepPoints": "sweep.front_end", "sweep_points": "sweep.front_end",
}

__all__ = ["__version__", *_WHERE]


__getattr__ = lazy_getattr(__name__, _WHERE, globals())


def __dir__() -> list[str]:
    return sorted(__all__)
