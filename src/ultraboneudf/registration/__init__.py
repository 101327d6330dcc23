"""Rigid registration of a pre-operative CT bone to the ultrasound surface (docs/registration.md).

At the end of the chain, beside the evaluation: it takes a CT mesh and what the pipeline made (a
point cloud or a reconstructed mesh, in mm) and gives the CT → ultrasound transform, searched
globally (no initial pose needed) and refined robustly against false echoes. Nothing below it in
the chain imports it. NumPy and SciPy only: PyTorch is not loaded.
"""

from .initial import pose_from_landmarks, read_init
from .options import RegisterOptions
from .solve import register
from .result import KIND, Registration

__all__ = ["KIND", "RegisterOptions", "Registration", "pose_from_landmarks", "read_init", "register"]
