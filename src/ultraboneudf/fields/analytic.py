"""Exact unsigned (and signed) distance fields of simple shapes, for tests, demos and benchmarks.

All lengths are in the field's own units (unit space in the pipeline). Gradients are exact
(closed form), except on the medial set where the distance is not differentiable and we return a
valid subgradient.
"""

from __future__ import annotations

import math

import torch

from .base import Field


class _Analytic(Field):
    def __init__(self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64):
        self.device = torch.device(device)
        self.dtype = dtype


class PlaneUDF(_Analytic):
    """|n·x − offset|: the plane with unit normal ``normal`` at signed distance ``offset``."""

    def __init__(self, normal=(0.0, 0.0, 1.0), offset: float = 0.0, signed: bool = False, **kw):
        super().__init__(**kw)
        n = torch.as_tensor(normal, dtype=self.dtype, device=self.device)
        self.normal = n / n.norm()
        self.offset = float(offset)
        self.signed = signed

    def _value(self, x):
        s = x @ self.normal - self.offset
        return s if self.signed else s.abs()

    def _value_and_grad(self, x):
        s = x @ self.normal - self.offset
        if self.signed:
            return s, self.normal.expand_as(x).clone()
        return s.abs(), torch.sign(s)[:, None] * self.normal


class SphereUDF(_Analytic):
    """|‖x − centre‖ − radius| (or the signed version)."""

    def __init__(self, radius: float = 0.3, centre=(0.0, 0.0, 0.0), signed: bool = False, **kw):
        super().__init__(**kw)
        self.radius = float(radius)
        self.centre = torch.as_tensor(centre, dtype=self.dtype, device=self.device)
        self.signed = signed

    def _value_and_grad(self, x):
        d = x - self.centre
        r = d.norm(dim=1)
        unit = d / r.clamp_min(1e-300)[:, None]
        s = r - self.radius
        if self.signed:
            return s, unit
        return s.abs(), torch.sign(s)[:, None] * unit

    def _value(self, x):
        return self._value_and_grad(x)[0]


class DiscUDF(_Analytic):
    """Distance to the flat disc {z = z0, x² + y² ≤ radius²}: an open surface with one boundary loop."""

    def __init__(self, radius: float = 0.4, z0: float = 0.0, **kw):
        super().__init__(**kw)
        self.radius = float(radius)
        self.z0 = float(z0)

    def _value_and_grad(self, x):
        rho = torch.hypot(x[:, 0], x[:, 1])
        dz = x[:, 2] - self.z0
        dr = (rho - self.radius).clamp_min(0.0)
        u = torch.hypot(dr, dz)
        radial = torch.stack([x[:, 0], x[:, 1], torch.zeros_like(rho)], 1) / rho.clamp_min(1e-300)[:, None]
        g = (dr[:, None] * radial + dz[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=x.dtype,
                                                               device=x.device)) / u.clamp_min(1e-300)[:, None]
        return u, g

    def _value(self, x):
        return self._value_and_grad(x)[0]


class TorusUDF(_Analytic):
    """|dist(x, circle of radius R in z = 0) − r|: a closed torus surface."""

    def __init__(self, major: float = 0.4, minor: float = 0.1, signed: bool = False, **kw):
        super().__init__(**kw)
        self.major, self.minor, self.signed = float(major), float(minor), signed

    def _value_and_grad(self, x):
        rho = torch.hypot(x[:, 0], x[:, 1])
        radial = torch.stack([x[:, 0], x[:, 1], torch.zeros_like(rho)], 1) / rho.clamp_min(1e-300)[:, None]
        q = torch.stack([rho - self.major, x[:, 2]], 1)
        dist = q.norm(dim=1)
        unit_q = q / dist.clamp_min(1e-300)[:, None]
        grad = unit_q[:, :1] * radial
        grad[:, 2] = grad[:, 2] + unit_q[:, 1]
        s = dist - self.minor
        if self.signed:
            return s, grad
        return s.abs(), torch.sign(s)[:, None] * grad

    def _value(self, x):
        return self._value_and_grad(x)[0]


def sphere_area(radius: float) -> float:
    return 4.0 * math.pi * radius**2


def torus_area(major: float, minor: float) -> float:
    return 4.0 * math.pi**2 * major * minor
