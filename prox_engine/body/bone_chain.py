"""A body's bone chain posed in one warp kernel, and its gradient in another.

Each body's thread walks its bones in depth order: Rodrigues' rotation of the bone's
axis-angle (identity for the bones the fit does not pose), turned by the bone's fixed
reference rotation, placed at its offset from its parent (the root: at the body's
translation), and composed onto the parent's pose. The backward pass walks the bones in
reverse, adds each bone's gradient (its subtree's included) into its parent's, and
differentiates Rodrigues' formula in closed form (as :class:`geometry._Rodrigues`).

In torch (Rodrigues' terms, the chain's products level by level, their gradients) a
skeleton's forward and backward pass took 803 small operations for one body and 1,200 for
eight, which on a CPU cost more in dispatch than in arithmetic; with these two kernels it
takes 181. warp is anny's own kernel compiler; ``prox setup`` warms its cache."""
from __future__ import annotations

import torch
import warp as wp

from ..warp_launch import CpuKernel


@wp.func
def _skew(a: wp.vec3) -> wp.mat33:
    return wp.mat33(0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0)


@wp.func
def _sine_terms(theta2: float) -> wp.vec2:
    """s = sin(t) / t and c = (1 - cos(t)) / t^2 of an angle t, by their series near 0."""
    if theta2 < 1e-8:
        return wp.vec2(1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0)
    theta = wp.sqrt(theta2 + 1e-16)
    return wp.vec2(wp.sin(theta) / theta, (1.0 - wp.cos(theta)) / wp.max(theta2, 1e-16))


@wp.func
def _rodrigues(a: wp.vec3) -> wp.mat33:
    """R = I + s K + c K^2, K the cross-product matrix of ``a``."""
    k = _skew(a)
    sc = _sine_terms(wp.dot(a, a))
    return wp.identity(n=3, dtype=float) + sc[0] * k + sc[1] * (k * k)


@wp.func
def _vee(m: wp.mat33) -> wp.vec3:
    return wp.vec3(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])


@wp.func
def _rodrigues_grad(a: wp.vec3, g: wp.mat33) -> wp.vec3:
    """The gradient in ``a`` of <g, R(a)>: a (s'/t <g, K> + c'/t <g, K^2>) + s vee(g) +
    c vee(g K^T + K^T g), the derivatives' ratios to t by their series below 0.1 rad."""
    k = _skew(a)
    t2 = wp.dot(a, a)
    sc = _sine_terms(t2)
    ds = float(0.0)
    dc = float(0.0)
    if t2 < 1e-2:
        ds = -1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0
        dc = -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0
    else:
        t = wp.sqrt(t2)
        cos = wp.cos(t)
        sin = wp.sin(t)
        ds = (t * cos - sin) / (t * t2)
        dc = (t * sin - 2.0 * (1.0 - cos)) / (t2 * t2)
    kt = wp.transpose(k)
    along = ds * wp.ddot(g, k) + dc * wp.ddot(g, k * k)
    return a * along + sc[0] * _vee(g) + sc[1] * _vee(g * kt + kt * g)


@wp.func
def _local(rotvecs: wp.array2d(dtype=wp.vec3), transl: wp.array(dtype=wp.vec3),
           offsets: wp.array2d(dtype=wp.vec3), slot: wp.array(dtype=wp.int32),
           turn: wp.array(dtype=wp.mat33), body: int, bone: int) -> wp.mat44:
    """Bone ``bone``'s pose in its parent's frame, in body ``body``."""
    s = slot[bone]
    r = wp.identity(n=3, dtype=float)
    if s < rotvecs.shape[1]:
        r = _rodrigues(rotvecs[body, s])
    m = turn[bone] * r
    t = offsets[wp.min(body, offsets.shape[0] - 1), bone]
    if bone == 0:
        t = transl[body]
    return wp.mat44(m[0, 0], m[0, 1], m[0, 2], t[0], m[1, 0], m[1, 1], m[1, 2], t[1],
                    m[2, 0], m[2, 1], m[2, 2], t[2], 0.0, 0.0, 0.0, 1.0)


@wp.kernel
def _pose(rotvecs: wp.array2d(dtype=wp.vec3), transl: wp.array(dtype=wp.vec3),
          offsets: wp.array2d(dtype=wp.vec3), slot: wp.array(dtype=wp.int32),
          turn: wp.array(dtype=wp.mat33), parent: wp.array(dtype=wp.int32),
          poses: wp.array2d(dtype=wp.mat44)):
    body = wp.tid()
    bones = slot.shape[0]
    for bone in range(bones):
        local = _local(rotvecs, transl, offsets, slot, turn, body, bone)
        p = parent[bone]
        if p < bones:
            local = poses[body, p] * local
        poses[body, bone] = local


@wp.kernel
def _pose_grad(rotvecs: wp.array2d(dtype=wp.vec3), transl: wp.array(dtype=wp.vec3),
               offsets: wp.array2d(dtype=wp.vec3), slot: wp.array(dtype=wp.int32),
               turn: wp.array(dtype=wp.mat33), parent: wp.array(dtype=wp.int32),
               poses: wp.array2d(dtype=wp.mat44), grads: wp.array2d(dtype=wp.mat44),
               rotvec_grad: wp.array2d(dtype=wp.vec3), transl_grad: wp.array(dtype=wp.vec3),
               offset_grad: wp.array2d(dtype=wp.vec3)):
    """``grads`` holds the loss's gradient in each pose on entry; each bone's subtree's
    is added into it on the way up (W_c = W_p K_c)."""
    body = wp.tid()
    bones = slot.shape[0]
    for i in range(bones):
        bone = bones - 1 - i
        g = grads[body, bone]
        p = parent[bone]
        local_grad = g
        if p < bones:
            local = _local(rotvecs, transl, offsets, slot, turn, body, bone)
            local_grad = wp.transpose(poses[body, p]) * g
            grads[body, p] = grads[body, p] + g * wp.transpose(local)
        shift = wp.vec3(local_grad[0, 3], local_grad[1, 3], local_grad[2, 3])
        if bone == 0:
            transl_grad[body] = shift
        else:
            offset_grad[body, bone] = shift
        s = slot[bone]
        if s < rotvecs.shape[1]:
            turned = wp.mat33(local_grad[0, 0], local_grad[0, 1], local_grad[0, 2],
                              local_grad[1, 0], local_grad[1, 1], local_grad[1, 2],
                              local_grad[2, 0], local_grad[2, 1], local_grad[2, 2])
            rotvec_grad[body, s] = _rodrigues_grad(rotvecs[body, s],
                                                   wp.transpose(turn[bone]) * turned)


class BoneChain:
    """A skeleton's fixed structure, in depth order: each bone's rotation among the
    axis-angles (``slot`` (J,); one past the last: identity), its fixed reference rotation
    ``turn`` (J, 3, 3) and its ``parent`` (J,; J for the root)."""

    def __init__(self, slot: torch.Tensor, turn: torch.Tensor, parent: torch.Tensor) -> None:
        self.bones = len(slot)
        self.structure = (slot.detach().to(torch.int32).contiguous(),
                          turn.detach().float().contiguous(),
                          parent.detach().to(torch.int32).contiguous())

    def __call__(self, rotvecs: torch.Tensor, transl: torch.Tensor, offsets: torch.Tensor
                 ) -> torch.Tensor:
        """Posed poses W (B, J, 4, 4), depth order, of the axis-angles ``rotvecs`` (B, P,
        3), the root at ``transl`` (B, 3), the other bones at ``offsets`` (B or 1, J, 3)
        from their parents, each in its parent's frame; differentiable in all three."""
        return _Posed.apply(rotvecs, transl, offsets, self)


_STRUCTURE = (wp.int32, wp.mat33, wp.int32)
_POSE = CpuKernel(_pose, (wp.vec3, wp.vec3, wp.vec3, *_STRUCTURE, wp.mat44))
_POSE_GRAD = CpuKernel(_pose_grad, (wp.vec3, wp.vec3, wp.vec3, *_STRUCTURE, wp.mat44,
                                    wp.mat44, wp.vec3, wp.vec3, wp.vec3))


class _Posed(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rotvecs: torch.Tensor, transl: torch.Tensor, offsets: torch.Tensor,
                chain: BoneChain) -> torch.Tensor:
        inputs = [t.detach().float().contiguous() for t in (rotvecs, transl, offsets)]
        poses = torch.empty(len(rotvecs), chain.bones, 4, 4)
        _POSE(len(rotvecs), *inputs, *chain.structure, poses)
        ctx.save_for_backward(*inputs, poses)
        ctx.chain = chain
        return poses

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        *inputs, poses = ctx.saved_tensors
        rotvecs, transl, offsets = inputs
        grads = grad.float().contiguous().clone()  # the kernel adds subtrees into it
        rotvec_grad, transl_grad = torch.zeros_like(rotvecs), torch.zeros_like(transl)
        offset_grad = torch.zeros(len(rotvecs), *offsets.shape[1:])
        _POSE_GRAD(len(rotvecs), *inputs, *ctx.chain.structure, poses, grads, rotvec_grad,
                   transl_grad, offset_grad)
        if len(offsets) != len(rotvecs):  # one set of offsets for every body
            offset_grad = offset_grad.sum(0, keepdim=True)
        return rotvec_grad, transl_grad, offset_grad, None
