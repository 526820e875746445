"""Geometry kernels whose gradients are written out instead of traced by autograd."""
from __future__ import annotations

import pytest
import torch

from prox_engine.geometry import _rodrigues_terms, axis_angle_to_matrix


def _traced(aa: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula as plain tensor operations, for autograd to differentiate."""
    k, s, c, _ = _rodrigues_terms(aa)
    return torch.eye(3, dtype=aa.dtype).expand(k.shape) + s[..., None] * k + c[..., None] * (k @ k)


@pytest.mark.parametrize("angle", [0.0, 1e-5, 0.05, 0.0999, 0.1001, 1.0, 3.1])
def test_rodrigues_gradient_is_autograds(angle):
    """The closed-form gradient of axis_angle_to_matrix matches autograd's trace of the
    formula in float64 on both sides of the series' 0.1 rad threshold and at zero, and
    the matrices are rotations."""
    torch.manual_seed(1)
    axes = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64), dim=1)
    aa = (axes * angle).requires_grad_(True)
    weights = torch.randn(64, 3, 3, dtype=torch.float64)
    mine = axis_angle_to_matrix(aa)
    ours, = torch.autograd.grad((mine * weights).sum(), aa)
    theirs, = torch.autograd.grad((_traced(aa) * weights).sum(), aa)
    torch.testing.assert_close(ours, theirs, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(mine.transpose(1, 2) @ mine,
                               torch.eye(3, dtype=torch.float64).expand(64, 3, 3))
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (aa[:4].detach().requires_grad_(),))


def test_picked_vertices_are_the_indexed_ones_with_their_gradient():
    """``picked`` gathers and differentiates as ``points[:, ids]`` does, on one body and
    on several, ids repeated included (their gradients add)."""
    from prox_engine.geometry import picked

    g = torch.Generator().manual_seed(0)
    for bodies, ids in ((1, torch.tensor([5, 0, 9, 3])), (3, torch.tensor([7, 2, 7, 0, 11]))):
        points = torch.randn(bodies, 12, 3, generator=g)
        weights = torch.randn(bodies, len(ids), 3, generator=g)
        ours, theirs = points.clone().requires_grad_(), points.clone().requires_grad_()
        assert torch.equal(picked(ours, ids), theirs[:, ids])
        (picked(ours, ids) * weights).sum().backward()
        (theirs[:, ids] * weights).sum().backward()
        assert torch.allclose(ours.grad, theirs.grad) and ours.grad[:, ids].abs().min() > 0
