"""The keypoint terms' kernels against the torch forms they replace, values and gradients."""
from __future__ import annotations

import math

import pytest
import torch

from prox_engine.camera import Camera
from prox_engine.keypoint_terms import keypoint_data, plumb_shins, posed_terms, trunk_terms
from prox_engine.keypoints import ANKLES, KNEES, MID_HIP, N_KEYPOINTS, NECK
from prox_engine.losses import gmof

DISTORTED = Camera(512.0, 498.0, 301.5, 262.0, k=[0.12, -0.06, 0.004, -0.003, 0.02])


def _keypoints(batch: int, seed: int = 0) -> torch.Tensor:
    """Keypoints (B, 118, 3) scattered 1.5-4.5 m in front of the camera, some off to
    the side far enough for the lens distortion to matter."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(batch, N_KEYPOINTS, 3, generator=generator) * torch.tensor(
        [0.8, 0.8, 0.5])
    points[..., 2] += 3.0
    return points


def _projected(points: torch.Tensor, camera: Camera) -> torch.Tensor:
    z = points[..., 2:3].clamp_min(1e-3)
    x, y = (points[..., :2] / z).unbind(-1)
    k1, k2, p1, p2, k3 = camera.k
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd * camera.fx + camera.cx, yd * camera.fy + camera.cy], -1)


def _trunk_angle(points: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    trunk = points[:, NECK] - points[:, MID_HIP]
    return torch.atan2(torch.linalg.cross(trunk, up.expand_as(trunk)).norm(dim=-1), trunk @ up)


def _gradient(value: torch.Tensor, points: torch.Tensor, seed: int = 1) -> torch.Tensor:
    """The gradient of a random combination of the rows' values."""
    mix = torch.rand(value.shape, generator=torch.Generator().manual_seed(seed)) + 0.5
    (gradient,) = torch.autograd.grad((value * mix).sum(), points, retain_graph=True)
    return gradient


@pytest.mark.parametrize("camera", [Camera(512.0, 498.0, 301.5, 262.0, k=[0.0] * 5),
                                    DISTORTED])
def test_reprojection_is_the_robust_pixel_error_and_its_gradient(camera):
    """With and without lens distortion, one keypoint nearer than the 1 mm near plane
    (projected as if there, no pull in depth) and zero weights on the face."""
    points = _keypoints(3).requires_grad_(True)
    with torch.no_grad():
        points[1, 4] = torch.tensor([0.02, -0.01, 0.0005])
    target = torch.rand(3, N_KEYPOINTS, 2, generator=torch.Generator().manual_seed(2)) * 600
    weight = torch.rand(3, N_KEYPOINTS, generator=torch.Generator().manual_seed(3))
    weight[:, 67:] = 0.0
    if camera.k:  # that point does not project through the distortion polynomial
        weight[1, 4] = 0.0
    assert torch.allclose(_projected(points, camera), camera.project(points))
    ours = keypoint_data(points, camera, target, weight, 100.0)
    theirs = (weight * gmof(((_projected(points, camera) - target) ** 2).sum(-1), 100.0)).sum(1)
    assert torch.allclose(ours, theirs, rtol=1e-5)
    expected = _gradient(theirs, points)
    assert torch.allclose(_gradient(ours, points), expected, rtol=1e-4,
                          atol=1e-4 * float(expected.abs().max()))


def test_reprojection_ignores_unweighted_points_that_do_not_project():
    """A zero-weight keypoint behind the camera adds nothing through the distortion
    polynomial (the torch form read NaN there); a weighted NaN keypoint reads NaN."""
    points = _keypoints(2)
    points[:, 80] = torch.tensor([0.4, 0.3, -1.0])
    target = torch.full((2, N_KEYPOINTS, 2), 300.0)
    weight = torch.ones(2, N_KEYPOINTS)
    weight[:, 80] = 0.0
    points[1, 3] = math.nan
    value = keypoint_data(points, DISTORTED, target, weight, 100.0)
    assert math.isfinite(float(value[0])) and math.isnan(float(value[1]))


def test_trunk_terms_are_the_angle_to_up_and_their_gradients():
    """For trunks at 4-176 degrees from an up that is none of the camera's axes (exactly
    along it, the direction of the angle's gradient is float32 noise in both forms): the
    upright term is gmof(angle^2), the level term -rho^2 (1 - q)^2 within rho of level
    (exactly 0 beyond), and both gradients are those of the angle."""
    up = torch.nn.functional.normalize(torch.tensor([0.2, -0.9, 0.35]), dim=0)
    side = torch.nn.functional.normalize(torch.linalg.cross(up, torch.tensor([1.0, 0, 0])),
                                         dim=0)
    tips = torch.arange(3.75, 180.0, 7.5)
    points = _keypoints(len(tips))
    turned = torch.deg2rad(tips)[:, None]
    points[:, NECK] = points[:, MID_HIP] + 0.5 * (turned.cos() * up + turned.sin() * side)
    points.requires_grad_(True)
    upright, level = trunk_terms(points, up, 0.35, 0.4)
    angle = _trunk_angle(points, up)
    theirs_upright = gmof(angle ** 2, 0.35)
    off_level = ((angle - torch.pi / 2) / 0.4).square().clamp(max=1.0)
    theirs_level = -0.4 ** 2 * (1 - off_level).square()
    assert torch.allclose(upright, theirs_upright, atol=1e-6)
    assert torch.allclose(level, theirs_level, atol=1e-6)
    assert bool((level[(tips - 90).abs() > 24] == 0).all())
    for ours, theirs in [(upright, theirs_upright), (level, theirs_level)]:
        expected = _gradient(theirs, points)
        assert torch.allclose(_gradient(ours, points), expected, rtol=1e-4,
                              atol=1e-5 * float(expected.abs().max()))


def test_plumb_shins_value_and_gradient():
    """Only the cut legs' shins count, weighted by the trunk's uprightness squared, which
    passes no gradient: the trunk's keypoints get none."""
    up = torch.nn.functional.normalize(torch.tensor([-0.1, -0.95, 0.3]), dim=0)
    points = _keypoints(4, seed=5).requires_grad_(True)
    cut = torch.tensor([[True, False], [True, True], [False, True], [False, False]])
    ours = plumb_shins(points, up, cut)
    with torch.no_grad():
        trunk = points[:, NECK] - points[:, MID_HIP]
        uprightness = ((trunk @ up) / trunk.norm(dim=-1)).clamp(min=0)
    shins = points[:, ANKLES] - points[:, KNEES]
    theirs = uprightness ** 2 * (cut * (1 + (shins @ up) / shins.norm(dim=-1))).sum(1)
    assert torch.allclose(ours, theirs, atol=1e-6) and float(ours[3]) == 0.0
    gradient = _gradient(ours, points)
    assert torch.allclose(gradient, _gradient(theirs, points), atol=1e-6)
    assert float(gradient[:, [NECK, MID_HIP]].abs().max()) == 0.0


@pytest.mark.parametrize("legs_cut", [True, False])
def test_posed_terms_are_the_terms_each_on_its_own(legs_cut):
    """The four terms from one launch: the same values as each term's own, and the same
    gradient of any combination of them (up to the order of the sums)."""
    generator = torch.Generator().manual_seed(4)
    points = _keypoints(3)
    target = torch.rand(3, N_KEYPOINTS, 2, generator=generator) * 600
    weight = torch.rand(3, N_KEYPOINTS, generator=generator)
    up = torch.nn.functional.normalize(torch.tensor([0.2, -0.9, 0.35]), dim=0)
    cut = torch.tensor([[True, False], [False, False], [True, True]]) & legs_cut
    own = points.clone().requires_grad_(True)
    each = [keypoint_data(own, DISTORTED, target, weight, 100.0),
            *trunk_terms(own, up, 0.3, 0.4), plumb_shins(own, up, cut)]
    fused = points.clone().requires_grad_(True)
    together = posed_terms(fused, DISTORTED, target, weight, 100.0, up, 0.3, 0.4, cut)
    assert all(torch.equal(a, b) for a, b in zip(each, together))
    mix = torch.rand(4, 3, generator=generator) + 0.5
    expected = _gradient(sum((m * v) for m, v in zip(mix, each)), own)
    assert torch.allclose(_gradient(sum((m * v) for m, v in zip(mix, together)), fused),
                          expected, rtol=1e-5, atol=1e-6 * float(expected.abs().max()))
