"""Values whose gradient was worked out with them, for terms computed without autograd.

A term computed in a warp kernel, or in a few operations outside autograd, returns its
value (B,) or (B, T) through :func:`with_gradient` with its gradient in its input (B, T,
...): autograd then records one node, whose backward only scales that gradient, instead
of one node per operation (each 2-5 us on a keypoint evaluation's small tensors)."""
from __future__ import annotations

import torch


def with_gradient(x: torch.Tensor, value: torch.Tensor, gradient: torch.Tensor
                  ) -> torch.Tensor:
    """``value`` (B,) or (B, T) of ``x`` (B, ...), differentiable in ``x`` through its
    ``gradient`` (B, ...) or (B, T, ...) (d value[b, t] / d x[b])."""
    return _WithGradient.apply(x, value, gradient)


class _WithGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, value: torch.Tensor, gradient: torch.Tensor
                ) -> torch.Tensor:
        ctx.save_for_backward(gradient)
        ctx.terms = value.dim() == 2
        return value.to(x.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        (gradient,) = ctx.saved_tensors
        if not ctx.terms:
            scale = grad.view(-1, *[1] * (gradient.dim() - 1)).to(gradient.dtype)
            return scale * gradient, None, None
        mixed = grad[:, None].to(gradient.dtype) @ gradient.flatten(2)  # (B, 1, ...)
        return mixed.view(len(gradient), *gradient.shape[2:]), None, None
