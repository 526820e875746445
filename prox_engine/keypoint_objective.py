"""A stage's objective with its gradient worked out directly, without autograd.

The keypoint stages (global, body, detail, final: about 490 of a frame's 580 body rows)
read the keypoints and the pose alone. Through autograd each evaluation built and walked a graph
of some forty nodes, about 1 ms, most of it dispatch around the kernels. Here the body's
keypoint path (:meth:`BodyModel.keypoint_path`) poses the keypoints in its own kernels,
the keypoint terms' kernel gives their values and slopes (:func:`posed_values`), and the
slopes go back through the path's kernels: the same sum as :meth:`Fitter._terms`' terms,
term for term (tests/test_keypoint_objective.py). A scene stage with the shape held (a
warm-started frame's contact stage) goes the same way: the path skins the scene terms'
vertices too, the terms give their values and slopes in them (``mesh``), and those go back
through the skinning; through autograd, its hundred operations cost as much again as its
kernels."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .body.base import KeypointPath
from .lbfgs import Direct


class KeypointObjective(Direct):
    """Per row, the keypoint terms' values (data, upright trunk, level trunk, plumb shins
    and, in a warm-started frame, the temporal term; from ``posed``: keypoints -> values
    (B, C) and slopes (B, C, K, 3)) weighed by ``columns`` (B, C), plus the ``priors`` of
    the ``path`` (name -> weight), plus
    ``fixed`` (B,): the terms that do not move in this stage, plus, for a path with
    vertices, the ``mesh`` terms (vertices -> their weighted sum (B,) and its gradient in
    them). Gradients in the ``free`` parameters; ``count`` is told the rows of each
    evaluation."""

    def __init__(self, path: KeypointPath, free: list[str],
                 posed: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                 columns: np.ndarray, priors: dict[str, float], fixed: np.ndarray,
                 count: Callable[[int], None],
                 mesh: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None
                 ) -> None:
        self.path, self.free, self.posed, self.mesh = path, free, posed, mesh
        self.columns, self.priors, self.fixed, self.count = columns, priors, fixed, count

    def evaluate(self) -> tuple[np.ndarray, list[np.ndarray]]:
        keypoints = self.path.pose()
        value, slope = self.posed(keypoints)
        total = (value.numpy() * self.columns).sum(1) + self.fixed
        keypoint_grad = np.einsum("bc,bckd->bkd", self.columns, slope.numpy())
        vertex_grad = None
        if self.mesh is not None:
            mesh_value, vertex_grad = self.mesh(self.path.vertices)
            total = total + mesh_value.numpy()
        grads = dict(self.path.gradients(torch.from_numpy(keypoint_grad), vertex_grad))
        found = self.path.priors()
        for name, weight in self.priors.items():
            value, slopes = found[name]
            total = total + weight * value
            for param, gradient in slopes.items():
                grads[param] = grads[param] + weight * gradient
        self.count(len(total))
        return total, [grads[name] for name in self.free]


def goal_distance(goal: torch.Tensor, points: slice, weight: float
                  ) -> Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """keypoints (B, K, 3) -> ``weight`` times the summed squared distance of the
    keypoints ``points`` from ``goal`` (B, n, 3), (B, 1), and its slope in the keypoints
    (B, 1, K, 3): a ``posed`` for :class:`KeypointObjective`."""
    def posed(keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        off = keypoints[:, points] - goal
        slope = torch.zeros(len(keypoints), 1, *keypoints.shape[1:])
        slope[:, 0, points] = 2 * weight * off
        return weight * off.square().sum((1, 2))[:, None], slope
    return posed
