"""Linear blend skinning in warp kernels that read only the bones a vertex is bound to.

anny binds each vertex to up to nine bones, 2.5 on average, and its kernel (and the
adjoint warp derives from it) visits all nine slots: 0.34 ms forward and 0.8 back for the
scene terms' 7,500 vertices, a fifth of a scene evaluation. These kernels read each
vertex's used slots from a compact list (:class:`Binding`: skipping empty slots in place
still cost a third more) and differentiate by hand: the vertex's gradient is sum_i w_i
R_i^T g (left out where the rest vertices are held, as while the shape is frozen: a
full-mesh forward and backward 0.12-0.18 ms faster), bone i's is w_i g [x; 1]^T."""
from __future__ import annotations

import torch
import warp as wp

from ..warp_launch import CpuKernel


@wp.kernel
def _skin(rest: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=wp.int32),
          bones: wp.array(dtype=wp.int32), weights: wp.array(dtype=wp.float32),
          transforms: wp.array2d(dtype=wp.mat44), posed: wp.array2d(dtype=wp.vec3)):
    b, v = wp.tid()
    x = rest[wp.min(b, rest.shape[0] - 1), v]
    result = wp.vec3(0.0, 0.0, 0.0)
    for i in range(start[v], start[v + 1]):
        result += weights[i] * wp.transform_point(transforms[b, bones[i]], x)
    posed[b, v] = result


@wp.kernel
def _skin_grad(rest: wp.array2d(dtype=wp.vec3), start: wp.array(dtype=wp.int32),
               bones: wp.array(dtype=wp.int32), weights: wp.array(dtype=wp.float32),
               transforms: wp.array2d(dtype=wp.mat44), grad: wp.array2d(dtype=wp.vec3),
               rest_wanted: wp.int32, rest_grad: wp.array2d(dtype=wp.vec3),
               transform_grad: wp.array2d(dtype=wp.mat44)):
    b, v = wp.tid()
    x = rest[wp.min(b, rest.shape[0] - 1), v]
    g = grad[b, v]
    along = wp.vec3(0.0, 0.0, 0.0)
    for i in range(start[v], start[v + 1]):
        w = weights[i]
        j = bones[i]
        if rest_wanted != 0:
            t = transforms[b, j]
            along += w * wp.vec3(t[0, 0] * g[0] + t[1, 0] * g[1] + t[2, 0] * g[2],
                                 t[0, 1] * g[0] + t[1, 1] * g[1] + t[2, 1] * g[2],
                                 t[0, 2] * g[0] + t[1, 2] * g[1] + t[2, 2] * g[2])
        wg = w * g
        wp.atomic_add(transform_grad, b, j, wp.mat44(
            wg[0] * x[0], wg[0] * x[1], wg[0] * x[2], wg[0],
            wg[1] * x[0], wg[1] * x[1], wg[1] * x[2], wg[1],
            wg[2] * x[0], wg[2] * x[1], wg[2] * x[2], wg[2],
            0.0, 0.0, 0.0, 0.0))
    if rest_wanted != 0:
        rest_grad[b, v] = along


_BINDING = (wp.int32, wp.int32, wp.float32)
_SKIN = CpuKernel(_skin, (wp.vec3, *_BINDING, wp.mat44, wp.vec3))
_SKIN_GRAD = CpuKernel(_skin_grad, (wp.vec3, *_BINDING, wp.mat44, wp.vec3, None, wp.vec3,
                                    wp.mat44))


class Binding:
    """Vertices bound to ``bones`` (V, n) int with ``weights`` (V, n) (summing to 1), their
    used slots (weight not 0) listed in order: vertex v's are start[v]..start[v + 1]."""

    def __init__(self, weights: torch.Tensor, bones: torch.Tensor) -> None:
        used = weights != 0
        self.start = torch.cat([torch.zeros(1, dtype=torch.int64), used.sum(1).cumsum(0)]).int()
        self.bones = bones[used].int()
        self.weights = weights[used].float()


def linear_blend_skinning(rest: torch.Tensor, binding: Binding, transforms: torch.Tensor
                          ) -> torch.Tensor:
    """Posed vertices (B, V, 3) of rest vertices (B or 1, V, 3) bound as ``binding`` says
    under skinning ``transforms`` (B, J, 4, 4); differentiable in the rest vertices and the
    transforms."""
    return _Skinned.apply(rest, binding, transforms)


class _Skinned(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rest: torch.Tensor, binding: Binding, transforms: torch.Tensor
                ) -> torch.Tensor:
        rest, transforms = (t.detach().float().contiguous() for t in (rest, transforms))
        posed = torch.empty(len(transforms), rest.shape[1], 3)
        _SKIN(posed.shape[:2], rest, binding.start, binding.bones, binding.weights,
              transforms, posed)
        ctx.save_for_backward(rest, transforms)
        ctx.binding = binding
        return posed

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        rest, transforms = ctx.saved_tensors
        transform_grad, rest_grad = skinning_gradients(rest, ctx.binding, transforms, grad,
                                                       ctx.needs_input_grad[0])
        return rest_grad, None, transform_grad


def skinning_gradients(rest: torch.Tensor, binding: Binding, transforms: torch.Tensor,
                       grad: torch.Tensor, rest_wanted: bool = False
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The gradients in the ``transforms`` (B, J, 4, 4) and, if ``rest_wanted``, in the
    ``rest`` vertices (as given: B or 1, V, 3; else None) of a loss whose gradient in the
    posed vertices of :func:`linear_blend_skinning` is ``grad`` (B, V, 3); float32,
    contiguous arguments."""
    rest_grad = torch.empty(len(transforms) if rest_wanted else 1, *rest.shape[1:])
    transform_grad = torch.zeros_like(transforms)
    _SKIN_GRAD((len(transforms), rest.shape[1]), rest, binding.start, binding.bones,
               binding.weights, transforms, grad.float().contiguous(), int(rest_wanted),
               rest_grad, transform_grad)
    if not rest_wanted:
        return transform_grad, None
    if len(rest) != len(transforms):  # one set of rest vertices for every body
        rest_grad = rest_grad.sum(0, keepdim=True)
    return transform_grad, rest_grad
