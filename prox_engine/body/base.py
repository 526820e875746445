"""The body-model interface the fitter relies on; anny and SMPL-X implement it."""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..with_gradient import with_gradient
from .by_frame import FRAME

Params = dict[str, torch.Tensor]


@dataclass
class BodyOutput:
    """A batch of posed bodies in the fitting frame (camera coordinates)."""

    vertices: torch.Tensor | None  # (B, V, 3); None when not asked for
    keypoints: torch.Tensor  # (B, 118, 3), OpenPose order (see prox_engine.keypoints)
    spheres: torch.Tensor | None = None  # (B, S, 4) collision proxies: centre, radius


@dataclass(eq=False)  # hashed by identity: a model may cache per subset
class VertexSubset:
    """Some of a body's vertices (``ids``, ascending), prepared by
    :meth:`BodyModel.vertex_subset`; ``forward(params, vertices=subset)`` poses only
    those. ``data`` holds a model's own per-subset buffers."""

    ids: torch.Tensor
    data: dict[str, Any] = field(default_factory=dict)


class KeypointPath(ABC):
    """A batch of bodies' keypoints (and, made with a vertex subset, those vertices) and
    posture priors with their gradients, worked out without autograd on the current values
    of the parameters it was made for (their memory, as the optimiser writes it), the
    shape held: what a keypoint stage reads, or with the subset a scene stage
    (:meth:`BodyModel.keypoint_path`). Buffers are reused: each result holds until the
    next call."""

    @abstractmethod
    def pose(self) -> torch.Tensor:
        """The keypoints (B, K, 3) float32, as :meth:`BodyModel.forward`'s."""

    @property
    @abstractmethod
    def vertices(self) -> torch.Tensor | None:
        """The subset's vertices (B, V, 3) float32 at the last :meth:`pose`, as
        :meth:`BodyModel.forward`'s; None for a path made without a subset."""

    @abstractmethod
    def gradients(self, keypoint_grad: torch.Tensor, vertex_grad: torch.Tensor | None = None
                  ) -> dict[str, np.ndarray]:
        """Per pose parameter, the gradient (float32, its shape) of a loss whose gradient
        in the keypoints of the last :meth:`pose` is ``keypoint_grad`` (B, K, 3) and in its
        :attr:`vertices` ``vertex_grad`` (B, V, 3) (None: the loss does not read them),
        float32."""

    @abstractmethod
    def priors(self) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
        """``pose_prior``, ``joint_limits``, ``bending`` and ``hand_prior``, as the model's
        own methods: each its value (B,) and its gradient in the parameters it reads."""


class BodyModel(ABC, torch.nn.Module):
    """Parameters -> vertices, faces, OpenPose-ordered keypoints, contact sets, part labels."""

    name: str
    faces: torch.Tensor  # (F, 3) int64
    keypoint_mask: torch.Tensor  # (118,) bool: which OpenPose points the model defines
    keypoint_weights: torch.Tensor  # (25, V): BODY_25 joints as weighted sums of vertices
    contact_parts: dict[str, torch.Tensor]  # part name -> vertex indices
    vertex_parts: list[str]  # per-vertex part label
    scene_vertices: torch.Tensor  # (V,) bool: vertices used by scene terms (no eyes/tongue)
    collision_pairs: torch.Tensor  # (P, 2) sphere index pairs that must not overlap

    postures: tuple[str, ...] = ("standing",)  # starting poses init_params can give
    lying_postures: tuple[str, ...] = ()  # those that start horizontal, not upright

    @abstractmethod
    def init_params(self, batch_size: int, posture: str = "standing") -> Params:
        """Parameters of a mean-shaped body at the origin in one of ``postures``."""

    @abstractmethod
    def forward(self, params: Params, vertices: bool | VertexSubset = True,
                spheres: bool = True) -> BodyOutput:
        """Pose the body. Without ``vertices`` a model may skip the mesh (keypoints and
        spheres only), which is what most fitting stages need; with a
        :class:`VertexSubset` the output's vertices are those of the subset, in its order.
        Without ``spheres`` the output has none (only self-penetration and the scale
        search's axes read them)."""

    @contextmanager
    def shape_expanded(self, params: Params, vertices: bool | VertexSubset
                       ) -> Iterator[Callable[[torch.Tensor], None]]:
        """Within it, a model may compute what depends on the shape from its first-order
        expansion about the shape of ``params``, for their rows and the ``vertices`` posed
        in one optimisation (a model whose shape is linear, or cheap, has nothing to
        gain). It gives a function that narrows the expansion to some rows of ``params``,
        for the optimisation to go on over those rows alone."""
        yield lambda rows: None

    def keypoint_path(self, params: Params, vertices: VertexSubset | None = None
                      ) -> KeypointPath | None:
        """The keypoints (and the ``vertices`` subset) and posture priors of ``params``
        (their shape held) with their gradients, without autograd; None (the default): the
        model has none, and its stages go through autograd."""
        return None

    def vertex_subset(self, ids: torch.Tensor) -> VertexSubset:
        """The vertices ``ids`` prepared for :meth:`forward` (a model that cannot pose a
        subset alone poses the whole mesh and picks them)."""
        return VertexSubset(torch.unique(ids))

    @abstractmethod
    def pose_prior(self, params: Params) -> torch.Tensor:
        """(B,) penalty of implausible body poses."""

    @abstractmethod
    def joint_limits(self, params: Params) -> torch.Tensor:
        """(B,) squared violation of anatomical joint limits (radians^2)."""

    @abstractmethod
    def bending_prior(self, params: Params) -> torch.Tensor:
        """(B,) penalty of elbows and knees bent the wrong way."""

    @abstractmethod
    def hand_prior(self, params: Params) -> torch.Tensor:
        """(B,) penalty of finger articulation."""

    @abstractmethod
    def shape_prior(self, params: Params) -> torch.Tensor:
        """(B,) negative log-likelihood of the body shape."""

    @abstractmethod
    def root_pivot(self, params: Params) -> torch.Tensor:
        """(B, 3) the point about which ``global_orient`` turns the body, before
        ``transl`` is added."""

    @abstractmethod
    def up_axis(self) -> torch.Tensor:
        """The model's up direction in its own (unposed root) frame, (3,)."""

    @abstractmethod
    def forward_axis(self) -> torch.Tensor:
        """The direction the model faces in its own frame, (3,)."""

    @abstractmethod
    def export(self, params: Params, index: int) -> dict:
        """JSON-ready parameters of one batch element."""

    def pose_group(self) -> list[str]:
        """Names of the parameters that describe the body pose (a learned prior may put
        a latent code here instead of joint rotations)."""
        return ["body_pose"]

    def arm_restarts(self, params: Params) -> list[Params]:
        """Copies of ``params`` with the left, the right and both arms restarted held
        forward; none for a model whose pose is a learned latent code."""
        return []

    def leg_postures(self, params: Params, thighs_kept: torch.Tensor | None = None
                     ) -> dict[str, Params]:
        """Copies of ``params`` with both legs posed as each start posture (standing,
        sitting, kneeling, crouching) has them, the rest kept, by posture; in the rows
        ``thighs_kept`` ((B,) bool) the shins alone, the thighs as fitted. None for a
        model whose pose is a learned latent code."""
        return {}

    def point_feet(self, params: Params, which: torch.Tensor) -> Params:
        """``params`` with the feet of ``which`` ((B, 2) bool, right then left) turned to
        full plantarflexion, toes along the shin; a model whose pose is a learned latent
        code keeps them as they are."""
        return params

    def relax_feet(self, params: Params, keep: torch.Tensor) -> Params:
        """``params`` with each foot's turn away from its neutral ankle (toes at right
        angles to the shin) scaled by ``keep`` ((B, 2), right then left: 1 keeps it, 0
        turns the foot to neutral); a model whose pose is a learned latent code keeps
        them as they are."""
        return params

    def prox_result(self, params: Params, index: int) -> dict | None:
        """The arrays of a PROX/SMPLify-X ``000.pkl`` for models that have one (SMPL-X)."""
        return None

    @abstractmethod
    def shape_group(self) -> list[str]:
        """Names of the parameters that describe body shape (frozen in sequence mode)."""

    def relative_size(self, params: Params) -> torch.Tensor:
        """(B,) each body's height (:meth:`rest_height`) over the prior-mean body's,
        exactly 1 where the shape is the mean."""
        mean, names = self.init_params(1), self.shape_group()
        if all(torch.equal(params[n], mean[n].expand_as(params[n])) for n in names):
            return torch.ones(len(params[names[0]]))
        with torch.no_grad():
            return self.rest_height(params) / self.rest_height(mean)

    def rest_height(self, params: Params) -> torch.Tensor:
        """(B,) a measure of each body's height by its shape alone, for comparing sizes:
        its :meth:`stature` unless a model has a cheaper measure."""
        return self.stature(params)

    def stature(self, params: Params) -> torch.Tensor:
        """(B,) each body's standing height (m) by its shape alone: its standing mesh's
        span along :meth:`up_axis`."""
        names = self.shape_group()
        standing = self.init_params(len(params[names[0]]))
        standing.update({n: params[n].detach() for n in names})
        if FRAME in params:
            standing[FRAME] = params[FRAME]
        along = self(standing, spheres=False).vertices @ self.up_axis()
        return along.max(1).values - along.min(1).values

    @property
    def num_vertices(self) -> int:
        return len(self.vertex_parts)


def limit_excess(pose: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """(B,) squared excess of joint rotations ``pose`` (B, J, 3) beyond ``low``..``high``
    (J, 3), summed (radians^2): a body model's joint limits, with their gradient."""
    held = pose.detach()
    over = held - held.clamp(low, high)
    return with_gradient(pose, over.square().sum((1, 2)), 2 * over)
