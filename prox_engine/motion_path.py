"""Sequence mode's choice, frame by frame, between a frame's warm-started fit and its fit
from scratch: the path through the frames' candidate fits along which the body moves least.

A chain of warm-started fits carries its anchor's placement and posture to every frame, right
or wrong (a kneeler anchored 40 cm near stays near); a frame fitted alone is right or wrong
by itself. People move little from one frame to the next, and a wrong fit of either kind
sits apart from its neighbours: the path whose summed motion (each step the mean distance
between the two fits' vertices) is least keeps, per frame, the fit that agrees with the
frames around it (Viterbi over two states a frame).

A chain moves little by construction (each fit starts from, and is held near, the one
before it), so a chain anchored wrong is a smooth path the fits from scratch, each right
or wrong by itself, can seldom undercut. Each candidate is also charged how far it is, on
average, from the other frames' fits from scratch (``evidence``): independent of the chain
and of one another, those that are right agree, and a chain carrying a wrong anchor sits
apart from all of them."""
from __future__ import annotations

import torch


def motion(a: torch.Tensor, b: torch.Tensor) -> float:
    """How far a body moves between two fits: the mean distance (m) between their vertices
    (V, 3), the same frame of reference."""
    return float((a - b).norm(dim=-1).mean())


def least_motion_path(candidates: list[list[torch.Tensor]],
                      before: torch.Tensor | None = None,
                      evidence: list[torch.Tensor] | None = None,
                      weight: float = 0.0) -> list[int]:
    """For frames in order, each with its candidate fits' vertices (one or more), the
    candidate of each frame on the path of least summed motion, from ``before`` (the
    vertices of the fit kept for the frame before them) where given, plus ``weight`` times
    each kept candidate's mean motion to the other frames' ``evidence`` (their fits from
    scratch, one a frame); of equal paths, the one with the earlier candidates."""
    if not candidates:
        return []
    apart = [[weight * consensus_distance(c, evidence, f) if evidence and weight else 0.0
              for c in frame] for f, frame in enumerate(candidates)]
    cost = [apart[0][k] + (0.0 if before is None else motion(before, c))
            for k, c in enumerate(candidates[0])]
    back: list[list[int]] = []
    for f, (previous, current) in enumerate(zip(candidates, candidates[1:]), 1):
        steps = [[cost[i] + motion(p, c) + apart[f][k] for i, p in enumerate(previous)]
                 for k, c in enumerate(current)]
        back.append([min(range(len(s)), key=s.__getitem__) for s in steps])
        cost = [min(s) for s in steps]
    best = min(range(len(cost)), key=cost.__getitem__)
    path = [best]
    for came_from in reversed(back):
        best = came_from[best]
        path.append(best)
    return path[::-1]


def consensus_distance(body: torch.Tensor, evidence: list[torch.Tensor], frame: int) -> float:
    """The mean motion from ``body`` (vertices) to the fits ``evidence`` of the frames but
    ``frame``; 0 with no other frame."""
    others = [e for f, e in enumerate(evidence) if f != frame]
    return sum(motion(body, e) for e in others) / len(others) if others else 0.0
