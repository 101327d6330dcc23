"""Loss terms (§1.6): small pure functions of tensors. Distances are in unit space."""

from __future__ import annotations

import torch


def tangent_residual(q: torch.Tensor, u: torch.Tensor, g_hat: torch.Tensor, foot: torch.Tensor) -> torch.Tensor:
    """``r(q) = ĝ(q)·(q − f(q')) − u(q)`` (M,): signed distance from ``q`` to the plane through the
    dynamic nearest surface point ``foot`` with normal ``ĝ``, minus the predicted distance (Eq. 6)."""
    return (g_hat * (q - foot)).sum(dim=1) - u


def tangent_loss(residual: torch.Tensor, norm: str) -> torch.Tensor:
    """Mean ``|r|`` (``l1``, the official code) or mean ``r²`` (``l2``, the paper's Eq. 6)."""
    if norm == "l1":
        return residual.abs().mean()
    if norm == "l2":
        return residual.square().mean()
    raise ValueError(f"unknown tangent norm {norm!r}")


def pull_loss(moved: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``L_pull = mean ‖q' − t(q)‖²`` with the static nearest surface point ``t(q)`` (Eq. 3)."""
    return (moved - target).square().sum(dim=1).mean()


def global_shape_loss(u_anchor: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``L_GS`` = mean squared error between ``u(ρ)`` and the anchor targets (Eq. 7)."""
    return (u_anchor - target).square().mean()


def on_surface_loss(u_surface: torch.Tensor) -> torch.Tensor:
    """``L_OS = mean u(p)²`` over the surface rows (Eq. 9)."""
    return u_surface.square().mean()


def eikonal_loss(*grads: torch.Tensor) -> torch.Tensor:
    """``L_Eik`` = Σ (‖∇u‖ − 1)² over all given gradient sets divided by their total count (Eq. 10)."""
    total = sum((g.norm(dim=1) - 1.0).square().sum() for g in grads)
    return total / sum(len(g) for g in grads)
