"""Rows of a batch worked out frame by frame, so that a frame fits alike alone and batched.

A batch holds each frame's rows (its starts, restarts, probes) side by side. BLAS and torch's
vectorised kernels round a row's result by how many rows they are given and by where in
memory they lie: a matrix product of one to three rows rounds apart from one of four or
more, a sigmoid's last elements take a scalar path, and a product's gradient rounds by the
alignment of what it multiplies. L-BFGS grows such an ulp into a different fit (a kneeler
72 mm off alone, 531 mm in its batch). The few computations that mix a batch's rows that
way (the shape's blendshape products, the expansion's steps, the sum of a row's terms) go
through :func:`by_frame`, which hands them each frame's rows as the frame alone would have
them."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

FRAME = "frame"  # optional in Params: (B,) int64, the frame each row belongs to
# BLAS rounds a row of a matrix product alike in products of this many rows or more,
# wherever the row lies (measured with MKL, the rest pose's and the phenotypes' products:
# every row of 4 to 48 alike; 1 to 3 rows round another way): frames of that many rows
# each may share one product (:func:`rows_alike`).
ALIKE_ROWS = 4


class FrameRows:
    """The rows of each frame of a batch (``frames`` (B,): the frame of each row), in
    their order, as index tensors (``groups``, frames in order of their first row)."""

    def __init__(self, frames: torch.Tensor) -> None:
        ids = frames.tolist()
        first = {frame: row for row, frame in reversed(list(enumerate(ids)))}
        self.groups = [torch.tensor([row for row, frame in enumerate(ids) if frame == wanted])
                       for wanted in sorted(first, key=first.get)]
        self.order = torch.cat(self.groups).argsort()

    def split(self, rows: torch.Tensor) -> list[torch.Tensor]:
        """Each frame's rows of ``rows`` (B, ...), each a tensor of its own."""
        return [rows[group] for group in self.groups]

    def join(self, parts: list[torch.Tensor]) -> torch.Tensor:
        """Each frame's part (its rows, ...) put back in the rows' order."""
        return _Joined.apply(self.order, self.groups, *parts)


def rows_alike(frames: torch.Tensor | None) -> bool:
    """Whether every frame of ``frames`` has :data:`ALIKE_ROWS` rows or more."""
    return frames is None or int(frames.unique(return_counts=True)[1].min()) >= ALIKE_ROWS


def one_frame(frames: torch.Tensor | None) -> bool:
    """Whether the rows of ``frames`` (see :data:`FRAME`; None: unknown) are one frame's."""
    return frames is None or bool((frames == frames[0]).all())


def by_frame(fn: Callable[..., Any], frames: torch.Tensor | None, *rows: torch.Tensor) -> Any:
    """``fn`` of ``rows`` (tensors whose first dimension is the batch's), applied to each
    frame's rows apart (``frames`` (B,): the frame of each row; None: one frame), in their
    order, and its results (a tensor, or a tuple, list or dict of them) put back in the
    rows' order. One frame's rows go to ``fn`` as they are; frames whose rows are equal
    (the keypoint stages' mean shape) share one call where no gradient flows back."""
    if one_frame(frames):
        return fn(*rows)
    framed = FrameRows(frames)
    shared = not any(t.requires_grad for t in rows)
    done: list[tuple[list[torch.Tensor], Any]] = []
    parts = []
    for given in zip(*(framed.split(t) for t in rows)):
        found = next((result for inputs, result in done if shared and all(
            a.shape == b.shape and torch.equal(a, b) for a, b in zip(inputs, given))), None)
        if found is None:
            found = fn(*given)
            done.append((list(given), found))
        parts.append(found)

    def joined(values: list) -> Any:
        head = values[0]
        if isinstance(head, torch.Tensor):
            return framed.join(values)
        if isinstance(head, dict):
            return {key: joined([value[key] for value in values]) for key in head}
        return type(head)(joined(list(value)) for value in zip(*values))
    return joined(parts)


class _Joined(torch.autograd.Function):
    """Frames' results (each (rows of the frame, ...)) in the rows' order; back, each
    frame's gradient a tensor of its own, not a slice of the batch's (whose alignment
    would round a product's gradient apart)."""

    @staticmethod
    def forward(ctx, order: torch.Tensor, groups: list[torch.Tensor],
                *values: torch.Tensor) -> torch.Tensor:
        ctx.groups = groups
        return torch.cat(values).index_select(0, order)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple:
        return (None, None, *(grad.index_select(0, group) for group in ctx.groups))


def frame_products(step: torch.Tensor, framed: FrameRows, blocks: list[torch.Tensor]
                   ) -> torch.Tensor:
    """Each frame's rows of ``step`` (B, 1, k) times its own ``blocks`` (its rows, k, n),
    batched matrix products taken frame by frame as each frame alone takes them, in the
    rows' order (B, 1, n); its gradient in ``step`` so too."""
    return _FrameProducts.apply(step, framed, *blocks)


class _FrameProducts(torch.autograd.Function):
    """:func:`frame_products` in one node: the same products as autograd's, without a
    node for each frame's index, product and join (1.0 ms less per evaluation of a batch
    of 8's scene stages)."""

    @staticmethod
    def forward(ctx, step: torch.Tensor, framed: FrameRows, *blocks: torch.Tensor
                ) -> torch.Tensor:
        ctx.framed, ctx.blocks = framed, blocks
        return torch.cat([torch.bmm(step.index_select(0, group), block)
                          for group, block in zip(framed.groups, blocks)]
                         ).index_select(0, framed.order)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple:
        framed, blocks = ctx.framed, ctx.blocks
        step = grad.new_empty(len(framed.order), 1, blocks[0].shape[1])
        for group, block in zip(framed.groups, blocks):
            step[group] = grad.index_select(0, group).bmm(block.transpose(1, 2))
        return (step, None, *[None] * len(blocks))
