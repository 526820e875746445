"""Rows of a batch worked out frame by frame, so that a frame fits alike alone and batched.

A batch holds each frame's rows (its starts, restarts, probes) side by side. BLAS and torch's
vectorised kernels round a row's result by how many rows they are given and by where in
memory they lie: a matrix product of one to three rows rounds apart from one of four or
more, a sigmoid's last elements take a scalar path, and a gradient read from a slice of a
larger tensor rounds by the slice's alignment. L-BFGS grows such an ulp into a different fit
(a kneeler 72 mm off alone, 531 mm in its batch). The few computations that mix a batch's
rows that way (the shape's blendshape products, the expansion's steps, the sum of a row's
terms) go through :func:`by_frame`, which hands them each frame's rows as the frame alone
would have them."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

FRAME = "frame"  # optional in Params: (B,) int64, the frame each row belongs to


def by_frame(fn: Callable[..., Any], frames: torch.Tensor | None, *rows: torch.Tensor) -> Any:
    """``fn`` of ``rows`` (tensors whose first dimension is the batch's), applied to each
    frame's rows apart (``frames`` (B,): the frame of each row; None: one frame), in their
    order, and its results (a tensor, or a tuple, list or dict of them) put back in the
    rows' order. One frame's rows go to ``fn`` as they are."""
    if frames is None or bool((frames == frames[0]).all()):
        return fn(*rows)
    ids = frames.tolist()
    first = {frame: row for row, frame in reversed(list(enumerate(ids)))}
    groups = [torch.tensor([row for row, frame in enumerate(ids) if frame == wanted])
              for wanted in sorted(first, key=first.get)]
    parts = [fn(*(t[group] for t in rows)) for group in groups]

    def joined(values: list) -> Any:
        head = values[0]
        if isinstance(head, torch.Tensor):
            # put in place rather than concatenated: each part's gradient is then a tensor
            # of its own, not a slice (whose alignment would round a product's apart)
            out = head.new_zeros(len(ids), *head.shape[1:])
            for group, value in zip(groups, values):
                out = out.index_put((group,), value)
            return out
        if isinstance(head, dict):
            return {key: joined([value[key] for value in values]) for key in head}
        return type(head)(joined(list(value)) for value in zip(*values))
    return joined(parts)
