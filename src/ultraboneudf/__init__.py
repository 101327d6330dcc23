"""ultraboneudf: bone surface meshes (mm) from tracked ultrasound point clouds.

>>> import ultraboneudf
>>> points = ultraboneudf.load_points("scan.xyz")                  # (N, 3) mm
>>> rec = ultraboneudf.reconstruct(points)                        # doctest: +SKIP
>>> rec.save("bone.ply")                                         # mesh + bone.json sidecar
"""

from ._version import __version__
from .config import Config, preset
from .errors import InputError
from .evaluation import EvalResult, evaluate
from .io import load_mesh, load_points, save_mesh
from .pipeline import Reconstruction, reconstruct, reconstruct_many

__all__ = ["__version__", "Config", "preset", "InputError", "load_points", "load_mesh", "save_mesh",
           "reconstruct", "reconstruct_many", "Reconstruction", "evaluate", "EvalResult"]
