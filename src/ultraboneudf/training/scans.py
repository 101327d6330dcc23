"""The K fields one training loop optimises at once, behind one interface: inputs ``(K, M, 3)``,
outputs ``(K, M)``.

One scan (K = 1) is its own network, whatever its layers (skip connections included), wrapped so
that it takes and gives a leading scan axis (:class:`OneScan`): the operations are the network's
own, so its training is unchanged by the axis. Several scans (K > 1) are K networks of the same
widths stacked into ``(K, out, in)`` weight tensors (:class:`StackedMLP`): one batched matrix
product per layer for all of them, so the fixed per-step overhead (operator dispatch, the
optimiser, the nearest-neighbour call) is paid once per step instead of K times. The scans stay
independent: the total loss is the sum of theirs, so each network's gradient is its own loss's, and
Adam is element-wise, so one optimiser over the stacked weights is K independent optimisers.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from ..fields.mlp import DistanceMLP, value_and_grad


class OneScan(nn.Module):
    """One network ``net`` (any module mapping (M, 3) to (M,)) with a leading scan axis of length 1.
    ``explicit``: its input gradient by :meth:`DistanceMLP.value_and_grad` (else autograd)."""

    def __init__(self, net: nn.Module, explicit: bool = True) -> None:
        super().__init__()
        self.net, self.explicit = net, explicit
        # a DistanceMLP's hand-written sweep: weights shared, ``rows`` taken (:func:`evaluate_rows`)
        self.one_sweep = explicit and isinstance(net, DistanceMLP)

    def weights(self) -> list[torch.Tensor] | None:
        """A :class:`DistanceMLP`'s effective weights, computed once for the step's evaluations
        (``None`` for other networks, which compute their own)."""
        return self.net.weights() if self.one_sweep else None

    def forward(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None) -> torch.Tensor:
        return (self.net(x[0], weights) if self.one_sweep else self.net(x[0]))[None]

    def value_and_grad(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None,
                       rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``u`` (1, M) and ``∇u`` (1, M, 3), differentiable in the weights; ``rows``: the gradient
        of the first ``rows`` inputs only (a :class:`DistanceMLP`'s hand-written sweep only)."""
        if self.one_sweep:
            u, g = self.net.value_and_grad(x[0], weights, rows)
        else:
            u, g = value_and_grad(self.net, x[0], create_graph=True, explicit=self.explicit)
        return u[None], g[None]

    def networks(self) -> list[nn.Module]:
        """The trained network (the module passed in, trained in place)."""
        return [self.net.eval()]


class StackedMLP(nn.Module):
    """K :class:`DistanceMLP` of the same widths (no skip) as stacked parameters ``v (K, out, in)``,
    ``g (K, out, 1)``, ``bias (K, out)``. Inputs ``(K, M, 3)``, outputs ``(K, M)``. ``explicit``:
    the input gradient by the hand-written sweep (else autograd)."""

    def __init__(self, nets: list[DistanceMLP], explicit: bool = True) -> None:
        super().__init__()
        first = nets[0]
        self.explicit = explicit
        self._template = (first,)   # in a tuple: not a submodule, its weights are not trained
        if any(n.skip for n in nets):
            raise ValueError("stacked training supports networks without skip connections")
        shapes = [[tuple(p.shape) for p in n.parameters()] for n in nets]
        if any(s != shapes[0] for s in shapes) or any(n.abs_output != first.abs_output for n in nets):
            raise ValueError("stacked networks must have the same widths and output")
        self.abs_output = first.abs_output
        self.weight_norm = [layer.weight_norm for layer in first.layers]
        stack = lambda name, i: nn.Parameter(torch.stack([getattr(n.layers[i], name).detach()  # noqa: E731
                                                          for n in nets]).clone())
        self.v = nn.ParameterList([stack("v", i) for i in range(len(first.layers))])
        self.bias = nn.ParameterList([stack("bias", i) for i in range(len(first.layers))])
        self.g = nn.ParameterList([stack("g", i) if wn else nn.Parameter(torch.zeros(0), requires_grad=False)
                                   for i, wn in enumerate(self.weight_norm)])

    @property
    def one_sweep(self) -> bool:
        """Whether :meth:`value_and_grad` takes ``rows`` (the hand-written sweep; :func:`evaluate_rows`)."""
        return self.explicit

    def weights(self) -> list[torch.Tensor]:
        """The effective weights ``(K, out, in)`` of every layer."""
        return [v * (g / v.norm(dim=2, keepdim=True)) if wn else v
                for v, g, wn in zip(self.v, self.g, self.weight_norm)]

    def forward(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``u`` (K, M) of the inputs ``x`` (K, M, 3), with the effective ``weights`` when given."""
        weights = weights or self.weights()
        h = x
        last = len(weights) - 1
        for i, (w, b) in enumerate(zip(weights, self.bias)):
            h = torch.baddbmm(b[:, None, :], h, w.transpose(1, 2))
            if i < last:
                h = torch.relu(h)
        out = h.squeeze(-1)
        return out.abs() if self.abs_output else out

    def value_and_grad(self, x: torch.Tensor, weights: list[torch.Tensor] | None = None,
                       rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``u`` (K, M) and ``∇u`` (K, M, 3), differentiable in the weights: the hand-written
        backward sweep of :meth:`DistanceMLP.value_and_grad` batched over the K networks, or
        autograd's double backward when built with ``explicit=False``. ``rows``: the gradient of
        the first ``rows`` inputs only, (K, rows, 3) (hand-written sweep only)."""
        weights = weights or self.weights()
        if not self.explicit:
            x = x.detach().requires_grad_(True)
            u = self(x, weights)
            return u, torch.autograd.grad(u.sum(), x, create_graph=True)[0]
        h, acts = x, []
        last = len(weights) - 1
        for i, (w, b) in enumerate(zip(weights, self.bias)):
            z = torch.baddbmm(b[:, None, :], h, w.transpose(1, 2))
            if i < last:
                h = torch.relu(z)
                # the ReLU's mask: its derivative in the weights is zero, so it leaves the graph
                acts.append(h.detach() if rows is None else h.detach()[:, :rows])
        z = z.squeeze(-1)
        u = z.abs() if self.abs_output else z
        zr = z if rows is None else z[:, :rows]
        d = zr.sign()[..., None] if self.abs_output else torch.ones_like(zr)[..., None]
        for i in range(last, -1, -1):
            if i < last:
                d = torch.ops.aten.threshold_backward(d, acts[i], 0.0)
            d = torch.bmm(d, weights[i])
        return u, d

    def networks(self) -> list[DistanceMLP]:
        """K separate networks holding the trained weights (copies of the first one given)."""
        return self.unstack(self._template[0])

    def unstack(self, template: DistanceMLP) -> list[DistanceMLP]:
        """K separate networks (copies of ``template``) holding the trained weights."""
        nets = []
        for k in range(self.v[0].shape[0]):
            net = copy.deepcopy(template)
            with torch.no_grad():
                for layer, v, g, b in zip(net.layers, self.v, self.g, self.bias):
                    layer.v.copy_(v[k])
                    layer.bias.copy_(b[k])
                    if layer.weight_norm:
                        layer.g.copy_(g[k])
            nets.append(net.to(self.v[0].device).eval())
        return nets


def evaluate_rows(model: OneScan | StackedMLP, x: torch.Tensor, extra: list[torch.Tensor],
                  weights: list[torch.Tensor] | None, grad: bool = True
                  ) -> tuple[torch.Tensor, torch.Tensor | None, list[torch.Tensor]]:
    """The values ``u`` (K, M) of ``x`` (K, M, 3), with ``grad`` their input gradient (K, M, 3)
    (differentiable in the weights; else ``None``), and the values (K, Mᵢ) of each of ``extra``
    (K, Mᵢ, 3): one forward sweep over all the rows where the model's hand-written gradient sweep
    can stop at ``x``'s rows (``model.one_sweep``), else separate evaluations."""
    sizes = [x.shape[1], *(e.shape[1] for e in extra)]
    if not grad:
        u, *rest = model(torch.cat([x, *extra], dim=1), weights).split(sizes, dim=1)
        return u, None, rest
    if not model.one_sweep:
        u, g = model.value_and_grad(x, weights)
        return u, g, [model(e, weights) for e in extra]
    u, g = model.value_and_grad(torch.cat([x, *extra], dim=1), weights, rows=x.shape[1])
    u, *rest = u.split(sizes, dim=1)
    return u, g, rest
