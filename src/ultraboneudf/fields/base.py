"""The field interface every extractor talks to.

A field maps points ``(M, 3)`` to values ``(M,)`` and, on request, input gradients ``(M, 3)``.
Subclasses implement :meth:`Field._value` (and optionally :meth:`Field._value_and_grad`, which by
default uses autograd on ``_value``); callers use :meth:`Field.value` and
:meth:`Field.value_and_grad`, which evaluate in chunks so that any ``M`` fits in memory and return
results on the caller's device in the caller's dtype. Gradients are *raw* (not normalised); use
:func:`normalize` for unit directions (a zero gradient stays zero, §0.2).
"""

from __future__ import annotations

import torch

DEFAULT_CHUNK = 150_000


def normalize(g: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along the last axis; a (near-)zero vector stays the zero vector."""
    return g / g.norm(dim=-1, keepdim=True).clamp_min(eps)


class Field:
    """A scalar field on R³. ``device`` and ``dtype`` say where and in what precision it computes."""

    device: torch.device = torch.device("cpu")
    dtype: torch.dtype = torch.float64

    def _value(self, x: torch.Tensor) -> torch.Tensor:
        """Values (M,) at x (M, 3) on ``self.device`` in ``self.dtype``; may build an autograd graph."""
        raise NotImplementedError

    def _value_and_grad(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            u = self._value(x)
            (g,) = torch.autograd.grad(u.sum(), x)
        return u.detach(), g.detach()

    def _chunks(self, x: torch.Tensor, chunk: int | None):
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"field input must be (M, 3), got {tuple(x.shape)}")
        step = chunk or DEFAULT_CHUNK
        for i in range(0, x.shape[0], step):
            yield x[i:i + step].to(device=self.device, dtype=self.dtype)

    def value(self, x: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
        """Field values (M,) at ``x`` (M, 3), evaluated ``chunk`` points at a time."""
        out = []
        with torch.no_grad():
            for xc in self._chunks(x, chunk):
                out.append(self._value(xc).to(device=x.device, dtype=x.dtype))
        return torch.cat(out) if out else x.new_zeros(0)

    def value_and_grad(self, x: torch.Tensor, chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Values (M,) and raw input gradients (M, 3) at ``x``, evaluated in chunks."""
        us, gs = [], []
        for xc in self._chunks(x, chunk):
            u, g = self._value_and_grad(xc)
            us.append(u.to(device=x.device, dtype=x.dtype))
            gs.append(g.to(device=x.device, dtype=x.dtype))
        if not us:
            return x.new_zeros(0), x.new_zeros(0, 3)
        return torch.cat(us), torch.cat(gs)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.value(x)
