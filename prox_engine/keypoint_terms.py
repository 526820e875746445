"""The terms that read only the posed keypoints, each one warp kernel that writes the
term's value and its gradient in one pass.

A keypoint stage's evaluation is about a millisecond, and before these kernels half of it
was the reprojection, trunk and shin terms: some 150 small torch operations forward, as
many nodes backward, at 2-5 us each for (B, 118, 3) tensors. Here each term is one launch
and one autograd node whose backward only scales the gradient written with the value."""
from __future__ import annotations

import functools

import torch
import warp as wp

from .camera import Camera
from .keypoints import ANKLES, KNEES, MID_HIP, NECK
from .warp_launch import CpuKernel
from .with_gradient import with_gradient

NEAREST_DEPTH = wp.constant(1e-3)  # m: nearer points project as if this deep, not pulled


@wp.func
def _robust(squared: float, rho: float) -> wp.vec2:
    """Geman-McClure of a squared residual (:func:`losses.gmof`) and its derivative."""
    rho2 = rho * rho
    return wp.vec2(rho2 * squared / (squared + rho2),
                   rho2 * rho2 / ((squared + rho2) * (squared + rho2)))


@wp.func
def reprojected(p: wp.vec3, target: wp.vec2, w: float, focal: wp.vec2, centre: wp.vec2,
                radial: wp.vec3, tangential: wp.vec2, rho: float) -> wp.vec4:
    """A camera-frame point's robust reprojection error, weighted by ``w``, and its
    gradient in the point: (value, d/dx, d/dy, d/dz)."""
    k1 = radial[0]
    k2 = radial[1]
    k3 = radial[2]
    p1 = tangential[0]
    p2 = tangential[1]
    z = p[2]
    deep = float(1.0)
    if not (z > NEAREST_DEPTH) and z == z:  # not NaN: NaN passes through
        z = NEAREST_DEPTH
        deep = 0.0
    x = p[0] / z
    y = p[1] / z
    r2 = x * x + y * y
    scale = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    dscale = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r2 * r2  # d scale / d r2
    xd = x * scale + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * scale + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    eu = xd * focal[0] + centre[0] - target[0]
    ev = yd * focal[1] + centre[1] - target[1]
    robust = _robust(eu * eu + ev * ev, rho)
    gu = 2.0 * w * robust[1] * eu * focal[0]  # d term / d xd, d yd
    gv = 2.0 * w * robust[1] * ev * focal[1]
    cross = 2.0 * x * y * dscale
    gx = (gu * (scale + 2.0 * x * x * dscale + 2.0 * p1 * y + 6.0 * p2 * x)
          + gv * (cross + 2.0 * p1 * x + 2.0 * p2 * y))
    gy = (gu * (cross + 2.0 * p1 * x + 2.0 * p2 * y)
          + gv * (scale + 2.0 * y * y * dscale + 6.0 * p1 * y + 2.0 * p2 * x))
    return wp.vec4(w * robust[0], gx / z, gy / z, -deep * (gx * x + gy * y) / z)


@wp.func
def _data_row(points: wp.array2d(dtype=wp.vec3), target: wp.array2d(dtype=wp.vec2),
              weight: wp.array2d(dtype=wp.float32), focal: wp.vec2, centre: wp.vec2,
              radial: wp.vec3, tangential: wp.vec2, rho: float, b: int, column: int,
              value: wp.array2d(dtype=wp.float32), gradient: wp.array3d(dtype=wp.vec3)):
    """Row ``b``'s weighted robust reprojection error and its gradient, in ``column``."""
    total = float(0.0)
    for k in range(points.shape[1]):
        w = weight[b, k]
        slope = wp.vec3(0.0, 0.0, 0.0)
        if w != 0.0:
            term = reprojected(points[b, k], target[b, k], w, focal, centre, radial,
                               tangential, rho)
            total += term[0]
            slope = wp.vec3(term[1], term[2], term[3])
        gradient[b, column, k] = slope
    value[b, column] = total


@wp.func
def _trunk_row(points: wp.array2d(dtype=wp.vec3), up: wp.vec3, neck: int, mid_hip: int,
               upright_rho: float, level_rho: float, b: int, column: int,
               value: wp.array2d(dtype=wp.float32), gradient: wp.array3d(dtype=wp.vec3)):
    """Row ``b``'s upright and level terms and their gradients, in ``column`` and the next
    (see :func:`trunk_terms`)."""
    trunk = points[b, neck] - points[b, mid_hip]
    along = wp.dot(trunk, up)
    normal = wp.cross(trunk, up)
    across = wp.length(normal)
    angle = wp.atan2(across, along)
    # d angle / d trunk = (along d across - across d along) / |trunk|^2 (up is a unit)
    turn = wp.vec3(0.0, 0.0, 0.0)
    if across > 0.0:
        turn = along * wp.cross(up, normal) / across
    slope = (turn - across * up) / wp.dot(trunk, trunk)
    robust = _robust(angle * angle, upright_rho)
    value[b, column] = robust[0]
    gradient[b, column, neck] = 2.0 * angle * robust[1] * slope
    gradient[b, column, mid_hip] = -2.0 * angle * robust[1] * slope
    # level: -rho^2 (1 - q)^2, q = ((angle - pi/2) / rho)^2 clamped at 1
    off = angle - 0.5 * wp.pi
    q = off * off / (level_rho * level_rho)
    lying = float(0.0)
    if q < 1.0:
        lying = 4.0 * (1.0 - q) * off
    else:
        q = 1.0
    value[b, column + 1] = -level_rho * level_rho * (1.0 - q) * (1.0 - q)
    gradient[b, column + 1, neck] = lying * slope
    gradient[b, column + 1, mid_hip] = -lying * slope


@wp.func
def _plumb_row(points: wp.array2d(dtype=wp.vec3), up: wp.vec3, neck: int, mid_hip: int,
               knees: wp.vec2i, ankles: wp.vec2i, cut: wp.array2d(dtype=wp.float32), b: int,
               column: int, value: wp.array2d(dtype=wp.float32),
               gradient: wp.array3d(dtype=wp.vec3)):
    """Row ``b``'s plumb-shins term and its gradient, in ``column`` (see
    :func:`plumb_shins`)."""
    trunk = points[b, neck] - points[b, mid_hip]
    upright = wp.max(wp.dot(trunk, up) / wp.max(wp.length(trunk), 1e-9), 0.0)
    weight = upright * upright  # held constant: no gradient through the trunk
    total = float(0.0)
    for leg in range(2):
        shin = points[b, ankles[leg]] - points[b, knees[leg]]
        length = wp.max(wp.length(shin), 1e-9)
        cosine = wp.dot(shin, up) / length
        slope = wp.vec3(0.0, 0.0, 0.0)
        if cut[b, leg] != 0.0:
            total += 1.0 + cosine
            if wp.length(shin) > 1e-9:
                slope = weight * (up - cosine * shin / length) / length
        gradient[b, column, ankles[leg]] = slope
        gradient[b, column, knees[leg]] = -slope
    value[b, column] = weight * total


@wp.kernel
def _terms(points: wp.array2d(dtype=wp.vec3), target: wp.array2d(dtype=wp.vec2),
           weight: wp.array2d(dtype=wp.float32), focal: wp.vec2, centre: wp.vec2,
           radial: wp.vec3, tangential: wp.vec2, rho: float, up: wp.vec3, neck: int,
           mid_hip: int, upright_rho: float, level_rho: float, knees: wp.vec2i,
           ankles: wp.vec2i, cut: wp.array2d(dtype=wp.float32), columns: wp.vec3i,
           value: wp.array2d(dtype=wp.float32), gradient: wp.array3d(dtype=wp.vec3)):
    """The terms whose ``columns`` (data, trunk, plumb) are not negative, in them."""
    b = wp.tid()
    if columns[0] >= 0:
        _data_row(points, target, weight, focal, centre, radial, tangential, rho, b,
                  columns[0], value, gradient)
    if columns[1] >= 0:
        _trunk_row(points, up, neck, mid_hip, upright_rho, level_rho, b, columns[1], value,
                   gradient)
    if columns[2] >= 0:
        _plumb_row(points, up, neck, mid_hip, knees, ankles, cut, b, columns[2], value,
                   gradient)


_TERMS = CpuKernel(_terms, (wp.vec3, wp.vec2, wp.float32, *[None] * 12, wp.float32, None,
                            wp.float32, wp.vec3))
_NONE = {"target": torch.zeros(0, 0, 2), "weight": torch.zeros(0, 0),
         "cut": torch.zeros(0, 2)}  # what a term left out reads (nothing)


def keypoint_data(keypoints: torch.Tensor, camera: Camera, target: torch.Tensor,
                  weight: torch.Tensor, rho: float) -> torch.Tensor:
    """Robust reprojection error (B,) of camera-frame ``keypoints`` (B, K, 3): the sum of
    ``weight`` (B, K) = (joint weight * confidence)^2, as in SMPLify-X, times the
    Geman-McClure (``rho`` px) of the squared pixel distance between the projected keypoint
    and ``target`` (B, K, 2). A keypoint of weight 0 adds nothing, even where it does not
    project (behind the camera with lens distortion, where the torch form read NaN)."""
    value, gradient = _launch(keypoints, (0, -1, -1), 1, camera=camera, target=target,
                              weight=weight, rho=rho)
    return with_gradient(keypoints, value[:, 0], gradient[:, 0])


def lens(camera: Camera) -> tuple[wp.vec2, wp.vec2, wp.vec3, wp.vec2]:
    """The camera as :func:`reprojected` reads it: focal lengths, principal point, radial
    (k1, k2, k3) and tangential (p1, p2) distortion."""
    return _lens(camera.fx, camera.fy, camera.cx, camera.cy, *(list(camera.k) + [0.0] * 5)[:5])


@functools.lru_cache(maxsize=16)  # the same few vectors, launch after launch
def _lens(fx: float, fy: float, cx: float, cy: float, k1: float, k2: float, p1: float,
          p2: float, k3: float) -> tuple[wp.vec2, wp.vec2, wp.vec3, wp.vec2]:
    return wp.vec2(fx, fy), wp.vec2(cx, cy), wp.vec3(k1, k2, k3), wp.vec2(p1, p2)


def trunk_terms(keypoints: torch.Tensor, up: torch.Tensor, upright_rho: float,
                level_rho: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two terms (B,) of the angle between the trunk (BODY_25 mid-hip to neck) of
    camera-frame ``keypoints`` (B, K, 3) and world ``up`` (3,), a unit vector in camera
    coordinates:

    - upright: its robust square (Geman-McClure, ``upright_rho`` rad): standing and
      sitting people hold their trunks near vertical, and a trunk leaning toward or away
      from the camera projects almost alike;
    - level: a reward for a trunk lying level, -rho^2 (1 - (e / rho)^2)^2 for a trunk
      ``e`` radians from the horizontal (rho = ``level_rho``), about 2 e^2 - rho^2 near 0,
      exactly 0 with no gradient from rho on: a mattress holds a lying trunk level, while a
      trunk lying along the camera's rays projects almost alike pitched up toward the
      camera. Trunks rho or more from level (upright, seated, reclining) neither pay nor
      feel it, so their fits do not change at all."""
    value, gradient = _launch(keypoints, (-1, 0, -1), 2, up=up, upright_rho=upright_rho,
                              level_rho=level_rho)
    return with_gradient(keypoints, value, gradient).unbind(1)


def plumb_shins(keypoints: torch.Tensor, up: torch.Tensor, cut: torch.Tensor
                ) -> torch.Tensor:
    """(B,) how far the shins of the legs ``cut`` ((B, 2) bool, per leg of SHINS) of
    camera-frame ``keypoints`` (B, K, 3) are from hanging plumb: 1 + the cosine of each
    shin (knee to ankle) with world ``up`` (3,), a unit vector in camera coordinates, 0
    straight down, 2 straight up, summed over those legs. Weighted
    by the square of the trunk's uprightness (the cosine of mid-hip to neck with up,
    clamped at 0, held constant): a standing or seated person's lower legs hang about
    plumb, a lying one's do not. Exactly 0, and nothing computed, without such a leg."""
    if not bool(cut.any()):
        return keypoints.new_zeros(len(keypoints))
    value, gradient = _launch(keypoints, (-1, -1, 0), 1, up=up, cut=cut)
    return with_gradient(keypoints, value[:, 0], gradient[:, 0])


def posed_terms(keypoints: torch.Tensor, camera: Camera, target: torch.Tensor,
                weight: torch.Tensor, rho: float, up: torch.Tensor, upright_rho: float,
                level_rho: float, cut: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """:func:`keypoint_data`, :func:`trunk_terms`' two and :func:`plumb_shins` (each
    (B,)) in one launch and one autograd node: a keypoint stage's evaluation paid some 25
    us forward and back for each term's own. ``cut`` None: no leg is cut (the shins' term
    0, nothing computed)."""
    value, gradient = posed_values(keypoints, camera, target, weight, rho, up, upright_rho,
                                   level_rho, cut)
    return with_gradient(keypoints, value, gradient).unbind(1)


def posed_values(keypoints: torch.Tensor, camera: Camera, target: torch.Tensor,
                 weight: torch.Tensor, rho: float, up: torch.Tensor, upright_rho: float,
                 level_rho: float, cut: torch.Tensor | None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`posed_terms`' four values (B, 4) and their gradients in the keypoints (B, 4,
    K, 3), without autograd."""
    return _launch(keypoints, (0, 1, -1 if cut is None else 3), 4, camera=camera,
                   target=target, weight=weight, rho=rho, up=up, upright_rho=upright_rho,
                   level_rho=level_rho, cut=cut)


def _launch(keypoints: torch.Tensor, columns: tuple[int, int, int], count: int,
            camera: Camera | None = None, target: torch.Tensor | None = None,
            weight: torch.Tensor | None = None, rho: float = 1.0,
            up: torch.Tensor | None = None, upright_rho: float = 1.0,
            level_rho: float = 1.0, cut: torch.Tensor | None = None
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """The values (B, ``count``) and gradients (B, ``count``, K, 3) of the terms whose
    ``columns`` (data, trunk (two), plumb) are not negative, zero elsewhere."""
    points = _points(keypoints)
    value = torch.zeros(len(points), count)
    gradient = torch.zeros(len(points), count, *points.shape[1:])
    camera = camera or Camera(1.0, 1.0, 0.0, 0.0)
    world_up = _vector(*([0.0, 0.0, 1.0] if up is None else up.tolist()))
    _TERMS(len(points), points,
           _NONE["target"] if target is None else target.detach().float().contiguous(),
           _NONE["weight"] if weight is None else weight.detach().float().contiguous(),
           *lens(camera), float(rho), world_up, NECK, MID_HIP, float(upright_rho),
           float(level_rho), *_LEGS,
           _NONE["cut"] if cut is None else cut.float().contiguous(), _columns(*columns),
           value, gradient)
    return value, gradient


def _points(keypoints: torch.Tensor) -> torch.Tensor:
    """The keypoints as the kernels read them (the kernels never write them: no detach)."""
    if keypoints.dtype == torch.float32 and keypoints.is_contiguous():
        return keypoints
    return keypoints.detach().float().contiguous()


# The kernel's constant arguments, built once: a warp vector costs 1 us to build.
_LEGS = (wp.vec2i(*KNEES), wp.vec2i(*ANKLES))
_vector = functools.lru_cache(maxsize=16)(wp.vec3)
_columns = functools.lru_cache(maxsize=16)(wp.vec3i)
