"""Sequence mode's choice, frame by frame, between a frame's warm-started fit and its fit
from scratch: the path through the frames' candidate fits along which the body moves least.

A chain of warm-started fits carries its anchor's placement and posture to every frame, right
or wrong (a kneeler anchored 40 cm near stays near); a frame fitted alone is right or wrong
by itself. People move little from one frame to the next, and a wrong fit of either kind
sits apart from its neighbours: the path whose summed motion (each step the mean distance
between the two fits' vertices) is least keeps, per frame, the fit that agrees with the
frames around it (Viterbi over two states a frame). For the same reason a chain starts
from the frame whose fit from scratch moves least to the others' (:func:`medoid`)."""
from __future__ import annotations

import torch


def motion(a: torch.Tensor, b: torch.Tensor) -> float:
    """How far a body moves between two fits: the mean distance (m) between their vertices
    (V, 3), the same frame of reference."""
    return float((a - b).norm(dim=-1).mean())


def least_motion_path(candidates: list[list[torch.Tensor]],
                      before: torch.Tensor | None = None) -> list[int]:
    """For frames in order, each with its candidate fits' vertices (one or more), the
    candidate of each frame on the path of least summed motion, from ``before`` (the
    vertices of the fit kept for the frame before them) where given; of equal paths, the
    one with the earlier candidates."""
    if not candidates:
        return []
    cost = [0.0 if before is None else motion(before, c) for c in candidates[0]]
    back: list[list[int]] = []
    for previous, current in zip(candidates, candidates[1:]):
        steps = [[cost[i] + motion(p, c) for i, p in enumerate(previous)] for c in current]
        back.append([min(range(len(s)), key=s.__getitem__) for s in steps])
        cost = [min(s) for s in steps]
    best = min(range(len(cost)), key=cost.__getitem__)
    path = [best]
    for came_from in reversed(back):
        best = came_from[best]
        path.append(best)
    return path[::-1]


def medoid(bodies: list[torch.Tensor], among: list[int]) -> int:
    """Of the bodies ``among`` (indices into ``bodies``, vertices (V, 3) each), the one
    whose summed motion to all of them is least (of equals, the first)."""
    return min(among, key=lambda i: sum(motion(bodies[i], other) for other in bodies))
