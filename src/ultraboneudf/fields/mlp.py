"""The MLP distance field (§0.3, §1.5): ReLU layers, weight normalisation, geometric initialisation,
absolute-value output.

Weight normalisation is written out (``W = g · V / ‖V‖_row``) instead of using
``torch.nn.utils.parametrizations``: the parameters are the same (``V``, ``g`` of shape
``(out, 1)``, bias; ``out·(in + 2)`` per layer, 191,042 for the official network) and the forward
pass is cheaper.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .base import Field


class WNLinear(nn.Module):
    """Linear layer with optional weight normalisation along the output rows (PyTorch ``dim=0``)."""

    def __init__(self, v: torch.Tensor, bias: torch.Tensor, weight_norm: bool) -> None:
        super().__init__()
        self.weight_norm = weight_norm
        self.v = nn.Parameter(v)
        self.bias = nn.Parameter(bias)
        if weight_norm:
            # Initialised to the row norms so that the initial function equals the plain layer.
            self.g = nn.Parameter(v.norm(dim=1, keepdim=True))

    def weight(self) -> torch.Tensor:
        if not self.weight_norm:
            return self.v
        return self.v * (self.g / self.v.norm(dim=1, keepdim=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.addmm(self.bias, x, self.weight().T)


class DistanceMLP(nn.Module):
    """``dims = [3, *hidden, 1]``; ReLU after every layer but the last; ``|·|`` at the output if
    ``abs_output``. Input in unit space ``(M, 3)``, output ``(M,)`` in unit-space distance.

    ``skip``: indices ``l`` of layers whose input is ``[h, x]/√2`` (§0.3); the layer before each such
    ``l`` emits ``dims[l] − in_dim`` features so that widths are kept (CAP-UDF/FUNSR: ``(4,)``)."""

    def __init__(self, hidden: tuple[int, ...] = (64, 128, 128, 256, 256, 256), weight_norm: bool = True,
                 radius: float = 0.5, abs_output: bool = True, in_dim: int = 3,
                 generator: torch.Generator | None = None, skip: tuple[int, ...] = ()) -> None:
        super().__init__()
        dims = [in_dim, *hidden, 1]
        self.skip = frozenset(int(s) for s in skip)
        if any(s <= 0 or s >= len(dims) - 1 for s in self.skip):
            raise ValueError(f"skip layers must lie in 1..{len(dims) - 2}, got {sorted(self.skip)}")
        layers = []
        for i, (fan_in, fan_out) in enumerate(zip(dims[:-1], dims[1:])):
            if i + 1 in self.skip:
                fan_out = fan_out - in_dim  # the skip concatenation restores the width
            if i == len(dims) - 2:
                # last layer: output ≈ ‖x‖ − radius (the signed distance to a sphere) at initialisation
                v = torch.normal(math.sqrt(math.pi) / math.sqrt(fan_in), 1e-4, (fan_out, fan_in),
                                 generator=generator)
                b = torch.full((fan_out,), -float(radius))
            else:
                v = torch.normal(0.0, math.sqrt(2.0) / math.sqrt(fan_out), (fan_out, fan_in),
                                 generator=generator)
                b = torch.zeros(fan_out)
            layers.append(WNLinear(v, b, weight_norm))
        self.layers = nn.ModuleList(layers)
        self.abs_output = abs_output

    def weights(self) -> list[torch.Tensor]:
        """The effective weight ``(out, in)`` of every layer, for several evaluations in one step."""
        return [layer.weight() for layer in self.layers]

    def forward(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``u(x)`` (M,); ``weights``: :meth:`weights`, computed once for several calls."""
        weights = weights or self.weights()
        h = x
        last = len(self.layers) - 1
        for i, (layer, w) in enumerate(zip(self.layers, weights)):
            if i in self.skip:
                # √2 keeps the activation scale of the concatenated input (IGR convention)
                h = torch.cat([h, x], dim=-1) / math.sqrt(2.0)
            h = torch.addmm(layer.bias, h, w.T)
            if i < last:
                h = torch.relu(h)
        out = h.squeeze(-1)
        return out.abs() if self.abs_output else out

    def value_and_grad(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None,
                       rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``u(x)`` (M,) and ``∇u(x)`` (M, 3) from one forward sweep and a hand-written backward
        sweep of the ReLU network: ``∇u = s·w_Lᵀ D_{L−1} W_{L−1} ⋯ D_1 W_1`` with the ReLU masks
        ``D`` and the output sign ``s``. Built from ordinary tensor operations, so the result is
        differentiable in the weights (for losses on ∇u) at first order: cheaper than autograd's
        double backward, which differentiates through the backward graph of the forward pass.
        Equal to autograd's input gradient, including its conventions ``relu'(0) = 0`` and
        ``|·|'(0) = 0``. ``rows``: the gradient of the first ``rows`` inputs only, (rows, 3) (the
        others' values come from the same forward sweep); ``weights`` as in :meth:`forward`."""
        weights = weights or self.weights()
        h, acts = x, []
        root2 = math.sqrt(2.0)
        last = len(self.layers) - 1
        for i, (layer, w) in enumerate(zip(self.layers, weights)):
            if i in self.skip:
                h = torch.cat([h, x], dim=-1) / root2
            z = torch.addmm(layer.bias, h, w.T)
            if i < last:
                h = torch.relu(z)
                # the ReLU's mask: its derivative in the weights is zero, so it leaves the graph
                acts.append(h.detach() if rows is None else h.detach()[:rows])
        z = z.squeeze(-1)
        u = z.abs() if self.abs_output else z
        zr = z if rows is None else z[:rows]
        d = zr.sign()[:, None] if self.abs_output else torch.ones_like(zr)[:, None]  # du/dz_last
        grad_x = None
        for i in range(last, -1, -1):
            if i < last:
                # du/dz_i: zero where the ReLU is off; autograd's own op for this, differentiable
                # in d and free of a mask tensor and its dtype conversion
                d = torch.ops.aten.threshold_backward(d, acts[i], 0.0)
            d = d @ weights[i]                    # du/d(input of layer i)
            if i in self.skip:
                # the input was [h, x]/√2: split the gradient between the two parts
                d, dx = d[:, :-x.shape[1]] / root2, d[:, -x.shape[1]:] / root2
                grad_x = dx if grad_x is None else grad_x + dx
        grad_x = d if grad_x is None else grad_x + d
        return u, grad_x


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars (weight-norm magnitudes included)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def value_and_grad(net: nn.Module, x: torch.Tensor, create_graph: bool,
                   explicit: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``u(x)`` (M,) and ``∇u(x)`` (M, 3); with ``create_graph`` the gradient is differentiable
    (needed by losses that depend on ∇u). A :class:`DistanceMLP` uses its hand-written backward
    sweep (:meth:`DistanceMLP.value_and_grad`) unless ``explicit`` is false; other networks, and
    ``explicit=False``, use autograd."""
    if explicit and isinstance(net, DistanceMLP):
        if create_graph:
            return net.value_and_grad(x)
        with torch.no_grad():
            return net.value_and_grad(x)
    if not x.requires_grad:
        x = x.requires_grad_(True)
    u = net(x)
    (g,) = torch.autograd.grad(u, x, torch.ones_like(u), create_graph=create_graph)
    return u, g


class MLPField(Field):
    """A trained network as a :class:`Field`: float32 on its device, results cast to the caller's dtype."""

    def __init__(self, net: nn.Module) -> None:
        self.net = net.eval()
        first = next(net.parameters())
        self.device = first.device
        self.dtype = first.dtype

    def _value(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def _value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():  # autograd is needed by networks other than DistanceMLP
            u, g = value_and_grad(self.net, x.detach().clone(), create_graph=False)
        return u.detach(), g.detach()
