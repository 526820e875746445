"""body.by_frame: a batch's rows worked out frame by frame, exactly as each frame alone."""
from __future__ import annotations

import torch

from prox_engine.body.by_frame import FrameRows, by_frame, frame_products


def test_each_frames_rows_go_apart_in_order_and_come_back_in_place():
    """Rows of frames 1, 0, 1, 2 reach ``fn`` as frame 1's rows 0 and 2, then 0's, then
    2's, and every kind of result (a tensor, a tuple, a dict) returns in the rows'
    order; one frame's rows reach ``fn`` untouched."""
    rows = torch.arange(4.0)[:, None] * torch.ones(4, 2)
    seen = []

    def fn(values: torch.Tensor) -> tuple:
        seen.append(values[:, 0].tolist())
        return values * 10, {"sum": values.sum(1)}

    scaled, found = by_frame(fn, torch.tensor([1, 0, 1, 2]), rows)
    assert seen == [[0.0, 2.0], [1.0], [3.0]]
    assert torch.equal(scaled, rows * 10) and torch.equal(found["sum"], rows.sum(1))
    seen.clear()
    by_frame(fn, torch.tensor([4, 4, 4, 4]), rows)
    assert seen == [[0.0, 1.0, 2.0, 3.0]]


def test_a_product_and_its_gradient_round_as_each_frame_alone():
    """A batched product (the shape expansion's step times slopes) of six frames' rows,
    and the gradient back through it, equal bit for bit those of each frame alone: BLAS
    rounds a product by the number of rows and the gradient by where in memory it lies
    (concatenating the parts instead gave four of these six rows' gradients apart)."""
    torch.manual_seed(0)
    steps, slopes = torch.randn(6, 1, 6), torch.randn(6, 6, 843)
    weights = torch.randn(6, 1, 843)

    def gradient(rows: slice, frames: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
        step = steps[rows].clone().requires_grad_(True)  # each its own tensor, as the
        value = by_frame(torch.matmul, frames, step, slopes[rows].clone())  # fitter's are
        (value * weights[rows]).sum().backward()
        return value.detach(), step.grad

    value, grad = gradient(slice(0, 6), torch.arange(6))
    for row in range(6):
        alone_value, alone_grad = gradient(slice(row, row + 1), None)
        assert torch.equal(alone_value, value[row:row + 1])
        assert torch.equal(alone_grad, grad[row:row + 1])


def test_frame_products_and_their_gradient_are_each_frames_alone():
    """frame_products (the expansion's steps times each frame's own slopes, in one autograd
    node) gives each frame's rows, and their gradient, exactly as that frame's product
    alone, frames interleaved and of one or two rows."""
    torch.manual_seed(1)
    frames = torch.tensor([0, 1, 1, 2, 0])
    framed = FrameRows(frames)
    steps, slopes = torch.randn(5, 1, 6), torch.randn(5, 6, 843)
    weights = torch.randn(5, 1, 843)
    step = steps.clone().requires_grad_(True)
    value = frame_products(step, framed, framed.split(slopes))
    (value * weights).sum().backward()
    for group in framed.groups:
        alone = steps[group].clone().requires_grad_(True)
        product = alone @ slopes[group].clone()
        (product * weights[group].clone()).sum().backward()
        assert torch.equal(product.detach(), value.detach()[group])
        assert torch.equal(alone.grad, step.grad[group])
