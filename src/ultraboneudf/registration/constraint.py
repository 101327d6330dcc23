"""How firmly the ultrasound holds the pose: the motions of the CT it barely resists.

An ultrasound view of part of a bone can leave a motion almost free — the femoral shaft slides along
and turns about its own axis with hardly a change to the points' distances. Near the answer each
explained target point's distance to the CT changes to first order by ``n·(ω × (y − c) + t)`` under a
small motion ``(ω, t)`` (``n``: the CT's normal at the point's match). Measuring a motion by the
root mean square displacement it gives the CT's surface, the generalised eigenproblem of the two
quadratic forms yields six *sensitivities*: for each principal motion, the RMS change of the
explained points' distances per millimetre of CT displacement. 1: the points feel the motion fully
(a shift along the surface normal); near 0: they barely feel it, and a systematic error of the data
as small as 0.1 mm can move the answer by 0.1 / sensitivity mm along it.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import eigh

from .model import BoneModel
from .refine import tukey


def sensitivities(model: BoneModel, placed: np.ndarray, cutoff: float, surface: np.ndarray,
                  workers: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Sensitivities ``(6,)`` (ascending) and their motions ``(6, 6)`` (columns: rotation vector in
    radians, translation in mm, about the centre of ``surface``; each scaled to 1 mm RMS
    displacement of ``surface``) of the target points ``placed`` ``(N, 3)`` on the CT (CT frame),
    weighted as the ICP weights them at ``cutoff`` mm; ``surface`` ``(P, 3)``: CT samples that
    measure the displacement."""
    d, idx = model.tree.query(placed, workers=workers)
    w = tukey(d, cutoff)
    centre = surface.mean(axis=0)
    n = model.normals[idx]
    jac = np.concatenate([np.cross(placed - centre, n), n], axis=1)
    fit = (jac * w[:, None]).T @ jac / max(float(w.sum()), 1e-12)
    p = surface - centre
    # displacement of p under (ω, t) is ω × p + t = [-p]ₓ ω + t
    cross = np.zeros((len(p), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = p[:, 2], -p[:, 1], p[:, 0]
    cross = cross - np.swapaxes(cross, 1, 2)
    disp = np.concatenate([cross, np.broadcast_to(np.eye(3), cross.shape)], axis=2)   # (P, 3, 6)
    metric = np.einsum("pki,pkj->ij", disp, disp) / len(p)
    values, vectors = eigh(fit + 1e-12 * np.eye(6), metric)
    return np.sqrt(np.maximum(values, 0.0)), vectors


def weakest_motion(model: BoneModel, placed: np.ndarray, cutoff: float, surface: np.ndarray,
                   to_target: np.ndarray, workers: int = -1) -> dict:
    """The least-felt motion of the CT as a record for the registration's JSON, directions in the
    target frame (``to_target``: the CT → target transform): ``sensitivity`` (see the module's
    text), ``translation_mm`` (its shift of the CT's centre per mm of surface displacement),
    ``rotation_deg`` (its turn per mm) and ``rotation_axis`` (unit), and all six ``sensitivities``."""
    values, vectors = sensitivities(model, placed, cutoff, surface, workers)
    v = vectors[:, 0]
    r = to_target[:3, :3]
    angle = float(np.linalg.norm(v[:3]))
    axis = r @ (v[:3] / angle) if angle > 0 else np.zeros(3)
    shift = r @ v[3:]
    key = shift if np.linalg.norm(shift) > 1e-6 else axis
    if key[np.argmax(np.abs(key))] < 0:  # an eigenvector's sign is arbitrary: fix one, for repeatability
        axis, shift = -axis, -shift
    return {"sensitivity": round(float(values[0]), 4),
            "translation_mm": [round(float(x), 4) for x in shift],
            "rotation_deg": round(float(np.degrees(angle)), 4),
            "rotation_axis": [round(float(x), 4) for x in axis],
            "sensitivities": [round(float(x), 4) for x in values]}
