"""Loss terms (§1.6): small pure functions of tensors. Distances are in unit space.

The per-query terms reduce over the last axis, so the same function serves one scan (values
``(M,)`` → a scalar) and K scans trained together (``(K, M)`` → ``(K,)``); ``mask`` (same shape,
1 = a real entry) lets scans with different counts share one padded tensor.
"""

from __future__ import annotations

import torch

from ..geometry.neighbors import brute_force_nearest


def _mean(x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over the last axis, of the entries ``mask`` keeps (all when ``None``)."""
    if mask is None:
        return x.mean(dim=-1)
    return (x * mask).sum(dim=-1) / mask.sum(dim=-1)


def tangent_residual(q: torch.Tensor, u: torch.Tensor, g_hat: torch.Tensor, foot: torch.Tensor) -> torch.Tensor:
    """``r(q) = ĝ(q)·(q − f(q')) − u(q)`` (…, M): signed distance from ``q`` to the plane through the
    dynamic nearest surface point ``foot`` with normal ``ĝ``, minus the predicted distance (Eq. 6)."""
    return (g_hat * (q - foot)).sum(dim=-1) - u


def tangent_loss(residual: torch.Tensor, norm: str) -> torch.Tensor:
    """Mean ``|r|`` (``l1``, the official code) or mean ``r²`` (``l2``, the paper's Eq. 6)."""
    if norm == "l1":
        return _mean(residual.abs())
    if norm == "l2":
        return _mean(residual.square())
    raise ValueError(f"unknown tangent norm {norm!r}")


def warm_start_loss(u: torch.Tensor, distance: torch.Tensor) -> torch.Tensor:
    """``mean |u(q) − d(q)|``: the warm start's regression on the static distance target."""
    return _mean((u - distance).abs())


def far_field_loss(u: torch.Tensor, distance: torch.Tensor, threshold: float) -> torch.Tensor:
    """``mean |u(q) − d(q)|·[d(q) > threshold]`` over all the batch's queries: the far-field term
    (``loss.lambda_far``), which leaves the queries near the data to the main loss."""
    return _mean((u - distance).abs() * (distance > threshold))


def pull_loss(moved: torch.Tensor, target: torch.Tensor, norm: str = "squared") -> torch.Tensor:
    """``L_pull = mean ‖q' − t(q)‖²`` with the static nearest surface point ``t(q)`` (Eq. 3);
    ``norm="unsquared"`` gives ``mean ‖q' − t(q)‖`` (FUNSR's code, §4.3)."""
    sq = (moved - target).square().sum(dim=-1)
    if norm == "squared":
        return _mean(sq)
    if norm == "unsquared":
        # tiny ε: the norm's gradient is undefined where q' = t exactly
        return _mean((sq + 1e-12).sqrt())
    raise ValueError(f"unknown pull norm {norm!r}")


def consistency_chamfer_loss(targets: torch.Tensor, moved: torch.Tensor) -> torch.Tensor:
    """CAP-UDF's consistency-aware loss (§3.3): symmetric L1 Chamfer distance between the batch
    targets ``A = {t(q)}`` (K, 3) and the moved queries ``B = {q'}`` (K, 3), Euclidean (not squared).

    The matching is found without a graph and the matched distances are recomputed with one: the
    gradient of a minimum is the gradient of its arg-min term, so this equals differentiating the
    full matrix."""
    # chunked: a 20,000 × 20,000 stage-2 batch never materialises whole
    to_b = brute_force_nearest(targets, moved, chunk=4096)
    to_a = brute_force_nearest(moved, targets, chunk=4096)
    d_ab = ((targets - moved[to_b]).square().sum(dim=1) + 1e-12).sqrt()
    d_ba = ((moved - targets[to_a]).square().sum(dim=1) + 1e-12).sqrt()
    return 0.5 * (d_ab.mean() + d_ba.mean())


def sign_consistency_loss(g_hat: torch.Tensor, moved: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """FUNSR ``L_SCC = mean(1 − cos(ĝ(q), normalise(q' − t)))`` (§4.3 item 3); a zero offset gives
    cosine 0 (constant loss 1, no gradient)."""
    w = moved - target
    w = w / w.norm(dim=1, keepdim=True).clamp_min(1e-12)
    cos = (g_hat * w).sum(dim=1) / (g_hat.norm(dim=1) * w.norm(dim=1)).clamp_min(1e-8)
    return (1.0 - cos).mean()


def lsgan_discriminator_loss(d_real: torch.Tensor, d_fake: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN discriminator loss ``mean (D(real) − 1)² + mean D(fake)²`` (§4.3 item 4)."""
    return (d_real - 1.0).square().mean() + d_fake.square().mean()


def lsgan_generator_loss(d_fake: torch.Tensor) -> torch.Tensor:
    """Least-squares GAN generator term ``mean (D(fake) − 1)²`` (FUNSR's ``L_ADL``)."""
    return (d_fake - 1.0).square().mean()


def global_shape_loss(u_anchor: torch.Tensor, target: torch.Tensor, form: str = "per_anchor",
                      mask: torch.Tensor | None = None) -> torch.Tensor:
    """``L_GS`` of the anchors' outputs (…, G) against their targets (…, G): ``per_anchor``, the mean
    squared error (Eq. 7); ``broadcast``, the mean over all G × G output–target pairs, as the
    reference's ``nn.MSELoss`` of (G, 1) against (G,) computes it, in its closed form
    ``mean (u − mean t)² + var t`` (O(G) instead of G² memory)."""
    if form == "per_anchor":
        return _mean((u_anchor - target).square(), mask)
    if form == "broadcast":
        mean_t = _mean(target, mask)[..., None]
        return _mean((u_anchor - mean_t).square(), mask) + _mean((target - mean_t).square(), mask)
    raise ValueError(f"unknown L_GS form {form!r}")


def on_surface_loss(u_surface: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``L_OS = mean u(p)²`` over the surface rows (Eq. 9)."""
    return _mean(u_surface.square(), mask)


def eikonal_loss(g_surface: torch.Tensor, g_queries: torch.Tensor,
                 mask: torch.Tensor | None = None) -> torch.Tensor:
    """``L_Eik`` = Σ (‖∇u‖ − 1)² over the gradients at the surface points (…, S, 3; those ``mask``
    keeps) and at the batch queries (…, M, 3), divided by their total count (Eq. 10)."""
    a = (g_surface.norm(dim=-1) - 1.0).square()
    b = (g_queries.norm(dim=-1) - 1.0).square()
    if mask is None:
        return (a.sum(dim=-1) + b.sum(dim=-1)) / (a.shape[-1] + b.shape[-1])
    return ((a * mask).sum(dim=-1) + b.sum(dim=-1)) / (mask.sum(dim=-1) + b.shape[-1])
