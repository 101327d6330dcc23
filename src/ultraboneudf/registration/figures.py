"""Pictures of a registration: the CT bone placed in the ultrasound frame, coloured by each vertex's
distance (mm) to the nearest ultrasound point — blue where the ultrasound lies on the CT, red where
it is far or saw nothing. A PNG (several views, :mod:`~ultraboneudf.evaluation.render`) and an
interactive HTML page with the ultrasound points (:mod:`~ultraboneudf.evaluation.viewer`)."""

from __future__ import annotations

import numpy as np
import trimesh

from ..evaluation.render import DEFAULT_VMAX_MM, render_distance_image
from ..evaluation.viewer import viewer_html
from ..pictures import png_bytes
from .result import Registration


def _title(reg: Registration) -> str:
    conf = "" if reg.confidence is None else f", confidence {reg.confidence:.2f}"
    return (f"residual {reg.residual_mm:.2f} mm, overlap {100 * reg.overlap:.0f}%, "
            f"coverage {100 * reg.coverage:.0f}%{conf}")


def registration_png(ct: trimesh.Trimesh, reg: Registration, target_points: np.ndarray,
                     vmax: float = DEFAULT_VMAX_MM) -> bytes:
    """PNG bytes: the placed CT ``ct`` from three views, coloured by distance to ``target_points``
    ``(N, 3)`` (mm, target frame), clamped at ``vmax`` mm."""
    image = render_distance_image(reg.place(ct), np.asarray(target_points, dtype=np.float64)[:, :3],
                                  title=_title(reg), vmax=vmax, mean_mm=float("nan"))
    return png_bytes(image)


def registration_html(ct: trimesh.Trimesh, reg: Registration, target_points: np.ndarray,
                      vmax: float = DEFAULT_VMAX_MM) -> bytes:
    """A self-contained HTML viewer (UTF-8 bytes) of the placed CT, coloured as
    :func:`registration_png`, with the ultrasound points as a layer."""
    points = np.asarray(target_points, dtype=np.float64)[:, :3]
    page = viewer_html(reg.place(ct), reference=points, points=points, title=_title(reg), vmax=vmax,
                       mean_mm=float("nan"), label="CT bone")
    return page.encode("utf-8")
