"""The start search's rigid fit (:mod:`initialisation`) as one warp kernel that writes its
objective and gradient in one pass.

Hundreds of candidate starts a frame, each a posture's keypoints turned (axis-angle, by
Rodrigues' formula, on its own start orientation) and moved, are fitted to the keypoints
by L-BFGS in some sixty evaluations. In torch each evaluation took about a millisecond,
two thirds of it the rotation's formula and its closed-form gradient (:mod:`geometry`):
sixty small operations on (N, 3, 3) tensors."""
from __future__ import annotations

import torch
import warp as wp

from .camera import Camera
from .keypoint_terms import lens, reprojected
from .warp_launch import CpuKernel
from .with_gradient import with_gradient


@wp.func
def _cross_matrix(a: wp.vec3) -> wp.mat33:
    return wp.mat33(0.0, -a[2], a[1], a[2], 0.0, -a[0], -a[1], a[0], 0.0)


@wp.func
def _vee(m: wp.mat33) -> wp.vec3:
    """m_zy - m_yz, m_xz - m_zx, m_yx - m_xy (geometry._vee)."""
    return wp.vec3(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])


@wp.kernel
def _rigid(turn: wp.array(dtype=wp.vec3), transl: wp.array(dtype=wp.vec3),
           start: wp.array(dtype=wp.mat33), keypoints: wp.array2d(dtype=wp.vec3),
           target: wp.array2d(dtype=wp.vec2), weight: wp.array2d(dtype=wp.float32),
           centre: wp.array2d(dtype=wp.float32), depth: wp.array(dtype=wp.float32),
           tilt0: wp.array(dtype=wp.float32), model_up: wp.vec3, up: wp.vec3,
           focal: wp.vec2, principal: wp.vec2, radial: wp.vec3, tangential: wp.vec2,
           rho: float, depth_weight: float, tilt_weight: float,
           value: wp.array(dtype=wp.float32), gradient: wp.array2d(dtype=wp.vec3)):
    n = wp.tid()
    a = turn[n]
    # Rodrigues: Q = I + s K + c K^2 (geometry.axis_angle_to_matrix)
    t2 = wp.dot(a, a)
    theta = wp.sqrt(t2 + 1.0e-16)
    s = 1.0 - t2 / 6.0
    c = 0.5 - t2 / 24.0
    if not (t2 < 1.0e-8):
        s = wp.sin(theta) / theta
        c = (1.0 - wp.cos(theta)) / wp.max(t2, 1.0e-16)
    k = _cross_matrix(a)
    kk = k * k
    rotation = (wp.identity(n=3, dtype=float) + s * k + c * kk) * start[n]
    # The keypoints, the depth held at the torso's weighted centre, and the lean kept.
    data = float(0.0)
    centre_depth = float(0.0)
    for j in range(keypoints.shape[1]):
        p = rotation * keypoints[n, j] + transl[n]
        centre_depth += centre[n, j] * p[2]
    held = centre_depth - depth[n]
    tilt = wp.dot(rotation * model_up, up) - tilt0[n]
    pull = wp.vec3(0.0, 0.0, 0.0)  # d / d transl
    turned = 2.0 * tilt_weight * tilt * wp.outer(up, model_up)  # d / d rotation
    for j in range(keypoints.shape[1]):
        p = rotation * keypoints[n, j] + transl[n]
        slope = wp.vec3(0.0, 0.0, 2.0 * depth_weight * held * centre[n, j])
        w = weight[n, j]
        if w != 0.0:
            term = reprojected(p, target[n, j], w, focal, principal, radial, tangential, rho)
            data += term[0]
            slope += wp.vec3(term[1], term[2], term[3])
        pull += slope
        turned += wp.outer(slope, keypoints[n, j])
    value[n] = data + depth_weight * held * held + tilt_weight * tilt * tilt
    # Back through rotation = Q start and Q's formula (geometry._Rodrigues.backward).
    g = turned * wp.transpose(start[n])
    series = t2 < 1.0e-2
    t = wp.sqrt(wp.where(series, 1.0, t2))
    ds = -1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0
    dc = -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0
    if not series:
        ds = (t * wp.cos(t) - wp.sin(t)) / (t * t * t)
        dc = (t * wp.sin(t) - 2.0 * (1.0 - wp.cos(t))) / (t * t * t * t)
    along = ds * wp.ddot(g, k) + dc * wp.ddot(g, kk)
    kt = wp.transpose(k)
    gradient[n, 0] = a * along + s * _vee(g) + c * _vee(g * kt + kt * g)
    gradient[n, 1] = pull


_RIGID = CpuKernel(_rigid, (wp.vec3, wp.vec3, wp.mat33, wp.vec3, wp.vec2, wp.float32,
                            wp.float32, wp.float32, wp.float32, *[None] * 9, wp.float32,
                            wp.vec3))


def rigid_fit(turn: torch.Tensor, transl: torch.Tensor, start: torch.Tensor,
              keypoints: torch.Tensor, camera: Camera, target: torch.Tensor,
              weight: torch.Tensor, centre: torch.Tensor, depth: torch.Tensor,
              tilt0: torch.Tensor, model_up: torch.Tensor, up: torch.Tensor, rho: float,
              depth_weight: float, tilt_weight: float) -> torch.Tensor:
    """(N,) objective of N rigidly moved keypoint sets, differentiable in ``turn`` and
    ``transl`` (N, 3): ``keypoints`` (N, K, 3) turned by Q(``turn``) ``start`` (N, 3, 3)
    and moved by ``transl`` are p; the objective is the robust reprojection error of p
    (``weight`` (N, K) as :func:`keypoint_terms.keypoint_data`, ``rho`` px, against
    ``target`` (N, K, 2)) + ``depth_weight`` (sum_k ``centre``[k] p_k.z - ``depth``)^2 +
    ``tilt_weight`` ((rotation ``model_up``) . ``up`` - ``tilt0``)^2."""
    value = torch.empty(len(turn))
    gradient = torch.empty(len(turn), 2, 3)
    _RIGID(len(turn), _read(turn), _read(transl), _read(start), _read(keypoints),
           _read(target), _read(weight), _read(centre), _read(depth), _read(tilt0),
           wp.vec3(*model_up.tolist()), wp.vec3(*up.tolist()), *lens(camera), float(rho),
           float(depth_weight), float(tilt_weight), value, gradient)
    return with_gradient(torch.cat([turn, transl], 1), value, gradient.view(len(turn), 6))


def _read(x: torch.Tensor) -> torch.Tensor:
    """``x`` as the kernel reads it (it never writes it: no detach)."""
    return x.float().contiguous()
