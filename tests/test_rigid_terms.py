"""The start search's rigid-fit kernel against the torch form it replaces, in float64."""
from __future__ import annotations

import torch

from prox_engine.camera import Camera
from prox_engine.geometry import axis_angle_to_matrix
from prox_engine.losses import gmof
from prox_engine.rigid_terms import rigid_fit

CAMERA = Camera(512.0, 498.0, 301.5, 262.0, k=[0.12, -0.06, 0.004, -0.003, 0.02])


def _reference(turn, transl, start, keypoints, target, weight, centre, depth, tilt0,
               model_up, up):
    """The objective as initialisation wrote it in torch (float64 here)."""
    turned = axis_angle_to_matrix(turn) @ start
    points = keypoints @ turned.transpose(1, 2) + transl[:, None]
    held = ((centre * points[..., 2]).sum(1) - depth) ** 2
    tilt = (turned @ model_up) @ up - tilt0
    pixels = CAMERA.project(points)
    data = (weight * gmof(((pixels - target) ** 2).sum(-1), 100.0)).sum(1)
    return data + 7.0 * held + 1e4 * tilt ** 2


def test_rigid_fit_is_the_torch_objective_and_its_gradient():
    """Turns of about 30 degrees and of 1e-3 and 1e-5 rad (the formulas' series), starts
    in every orientation, an up that is none of the camera's axes, some keypoints
    unweighted; values and gradients within float32 rounding of the float64 form."""
    g = torch.Generator().manual_seed(0)
    n, k = 40, 25
    turn = torch.randn(n, 3, generator=g) * 0.5
    turn[:5] *= 1e-3
    turn[5:8] *= 1e-5
    transl = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    start = axis_angle_to_matrix(torch.randn(n, 3, generator=g))
    keypoints = torch.randn(n, k, 3, generator=g) * 0.4
    target = torch.rand(n, k, 2, generator=g) * 600
    weight = torch.rand(n, k, generator=g)
    weight[:, 20:] = 0.0
    centre = torch.rand(n, k, generator=g)
    centre = centre / centre.sum(1, keepdim=True)
    depth = torch.rand(n, generator=g) + 2.5
    up = torch.nn.functional.normalize(torch.tensor([0.1, -0.9, 0.3]), dim=0)
    model_up = torch.tensor([0.0, 1.0, 0.0])
    tilt0 = (start @ model_up) @ up + 0.05 * torch.randn(n, generator=g)
    mix = torch.rand(n, generator=g) + 0.5  # a random combination of the rows

    ours = [turn.clone().requires_grad_(True), transl.clone().requires_grad_(True)]
    value = rigid_fit(*ours, start, keypoints, CAMERA, target, weight, centre, depth, tilt0,
                      model_up, up, 100.0, 7.0, 1e4)
    gradient = torch.autograd.grad((value * mix).sum(), ours)
    exact = [turn.double().requires_grad_(True), transl.double().requires_grad_(True)]
    expected = _reference(*exact, *(t.double() for t in (start, keypoints, target, weight,
                                                         centre, depth, tilt0, model_up,
                                                         up)))
    expected_gradient = torch.autograd.grad((expected * mix.double()).sum(), exact)
    assert torch.allclose(value.double(), expected, rtol=1e-5)
    for got, want in zip(gradient, expected_gradient):
        assert torch.allclose(got.double(), want, rtol=1e-4, atol=1e-4 * float(want.abs().max()))
