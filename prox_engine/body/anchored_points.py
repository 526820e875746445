"""Points carried by posed bones, each the sum of its anchors' moves, in warp kernels.

anny's keypoints are weighted sums of vertices, so each is a sum over a few bones of the
bone's posed transform applied to an anchor [a; h] held in the bone's rest frame
(:meth:`AnnyBody._local_anchors`), or a hand bone's head, or zero (the face). In torch
that was a gather of the bones, a product, a scatter-add, a concatenation and a gather:
ten operations forward and as many backward on every evaluation, about 60 us. Here it is
one launch each way."""
from __future__ import annotations

import torch
import warp as wp

from ..warp_launch import CpuKernel


@wp.kernel
def _place(poses: wp.array2d(dtype=wp.mat44), anchors: wp.array2d(dtype=wp.vec3),
           weight: wp.array(dtype=wp.float32), slot: wp.array(dtype=wp.int32),
           start: wp.array(dtype=wp.int32), pair: wp.array(dtype=wp.int32),
           head: wp.array(dtype=wp.int32), points: wp.array2d(dtype=wp.vec3)):
    b, k = wp.tid()
    held = wp.min(b, anchors.shape[0] - 1)
    out = wp.vec3(0.0, 0.0, 0.0)
    if head[k] >= 0:
        m = poses[b, head[k]]
        out = wp.vec3(m[0, 3], m[1, 3], m[2, 3])
    for i in range(start[k], start[k + 1]):
        p = pair[i]
        m = poses[b, slot[p]]
        a = anchors[held, p]
        w = weight[p]
        out += wp.vec3(m[0, 0] * a[0] + m[0, 1] * a[1] + m[0, 2] * a[2] + m[0, 3] * w,
                       m[1, 0] * a[0] + m[1, 1] * a[1] + m[1, 2] * a[2] + m[1, 3] * w,
                       m[2, 0] * a[0] + m[2, 1] * a[1] + m[2, 2] * a[2] + m[2, 3] * w)
    points[b, k] = out


@wp.kernel
def _place_grad(poses: wp.array2d(dtype=wp.mat44), anchors: wp.array2d(dtype=wp.vec3),
                weight: wp.array(dtype=wp.float32), slot: wp.array(dtype=wp.int32),
                start: wp.array(dtype=wp.int32), pair: wp.array(dtype=wp.int32),
                head: wp.array(dtype=wp.int32), grad: wp.array2d(dtype=wp.vec3),
                pose_grad: wp.array2d(dtype=wp.mat44), anchor_grad: wp.array2d(dtype=wp.vec3)):
    b, k = wp.tid()
    held = wp.min(b, anchors.shape[0] - 1)
    g = grad[b, k]
    if head[k] >= 0:
        wp.atomic_add(pose_grad, b, head[k], wp.mat44(
            0.0, 0.0, 0.0, g[0], 0.0, 0.0, 0.0, g[1], 0.0, 0.0, 0.0, g[2],
            0.0, 0.0, 0.0, 0.0))
    for i in range(start[k], start[k + 1]):
        p = pair[i]
        m = poses[b, slot[p]]
        a = anchors[held, p]
        w = weight[p]
        wp.atomic_add(pose_grad, b, slot[p], wp.mat44(
            g[0] * a[0], g[0] * a[1], g[0] * a[2], g[0] * w,
            g[1] * a[0], g[1] * a[1], g[1] * a[2], g[1] * w,
            g[2] * a[0], g[2] * a[1], g[2] * a[2], g[2] * w,
            0.0, 0.0, 0.0, 0.0))
        wp.atomic_add(anchor_grad, b, p, wp.vec3(
            m[0, 0] * g[0] + m[1, 0] * g[1] + m[2, 0] * g[2],
            m[0, 1] * g[0] + m[1, 1] * g[1] + m[2, 1] * g[2],
            m[0, 2] * g[0] + m[1, 2] * g[1] + m[2, 2] * g[2]))


_STRUCTURE = (wp.float32, wp.int32, wp.int32, wp.int32, wp.int32)
_PLACE = CpuKernel(_place, (wp.mat44, wp.vec3, *_STRUCTURE, wp.vec3))
_PLACE_GRAD = CpuKernel(_place_grad, (wp.mat44, wp.vec3, *_STRUCTURE, wp.vec3, wp.mat44,
                                      wp.vec3))


class AnchoredPoints:
    """Output points each made of the anchor pairs whose ``pair_point`` (P,) is its row
    in ``source`` (K,), or of the head of the bone ``heads[row - rows]`` for the rows
    after the ``rows`` anchored ones, or zero past those; pair p is carried by the bone
    at ``slot[p]`` of the posed bones, with the weight ``weight[p]`` of its head."""

    def __init__(self, source: torch.Tensor, pair_point: torch.Tensor, slot: torch.Tensor,
                 weight: torch.Tensor, heads: torch.Tensor, rows: int) -> None:
        order = torch.argsort(pair_point, stable=True)
        lists = [order[pair_point[order] == row] for row in source.tolist()]
        self.start = torch.tensor([0] + [len(p) for p in lists]).cumsum(0).int()
        self.pair = torch.cat(lists).int()
        heads_of = torch.full((len(source),), -1, dtype=torch.int32)
        is_head = (source >= rows) & (source < rows + len(heads))
        heads_of[is_head] = heads[source[is_head] - rows].int()
        self.head, self.slot = heads_of, slot.int().contiguous()
        self.weight = weight.float().contiguous()

    def __call__(self, poses: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """Points (B, K, 3) of bones posed at ``poses`` (B, J, 4, 4) with ``anchors`` (B or
        1, P, 3) in their rest frames; differentiable in both."""
        return _Placed.apply(poses, anchors, self)


class _Placed(torch.autograd.Function):
    @staticmethod
    def forward(ctx, poses: torch.Tensor, anchors: torch.Tensor, layout: AnchoredPoints
                ) -> torch.Tensor:
        poses, anchors = poses.detach().contiguous(), anchors.detach().contiguous()
        points = torch.empty(len(poses), len(layout.head), 3)
        _PLACE(points.shape[:2], poses, anchors, layout.weight, layout.slot, layout.start,
               layout.pair, layout.head, points)
        ctx.save_for_backward(poses, anchors)
        ctx.layout = layout
        return points

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None]:
        poses, anchors = ctx.saved_tensors
        layout = ctx.layout
        pose_grad = torch.zeros_like(poses)
        anchor_grad = torch.zeros(len(poses), *anchors.shape[1:])
        _PLACE_GRAD(grad.shape[:2], poses, anchors, layout.weight, layout.slot, layout.start,
                    layout.pair, layout.head, grad.float().contiguous(), pose_grad,
                    anchor_grad)
        if len(anchors) != len(poses):  # one set of anchors for every body
            anchor_grad = anchor_grad.sum(0, keepdim=True)
        return pose_grad, anchor_grad, None
