"""anny's keypoints (and a vertex subset's) and posture priors with their gradients,
without autograd.

A keypoint stage reads nothing of the body but its keypoints and its pose. Through torch,
an evaluation was some forty autograd nodes and two hundred operations, each a few
microseconds of dispatch around a few nanoseconds of arithmetic: about 1 ms, of which the
bone chain's and the anchors' kernels took a tenth. Here those kernels run on buffers
held for the stage, and the priors are numpy on the pose's hundred numbers. A scene stage
with the shape held reads the scene terms' vertices too: the skinning kernels pose them
and take their gradient back to the bones' poses."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from .anchored_points import _PLACE, _PLACE_GRAD
from .base import KeypointPath, Params, VertexSubset
from .by_frame import FRAME
from .bone_chain import _POSE, _POSE_GRAD
from .skinning import linear_blend_skinning, skinning_gradients

if TYPE_CHECKING:
    from .anny_body import AnnyBody


class AnnyKeypointPath(KeypointPath):
    """The keypoints (and the ``vertices`` subset's, skinned as :class:`AnnyBody` skins
    them) of anny bodies with the shape of ``params`` held (:meth:`pose`) and the
    parameters' gradients from theirs (:meth:`gradients`), on ``params``' current values;
    the posture priors as :class:`AnnyBody`'s (:meth:`priors`)."""

    def __init__(self, body: AnnyBody, params: Params,
                 vertices: VertexSubset | None = None) -> None:
        with torch.no_grad():
            rest = body._rest(params["shape"], vertices, frames=params.get(FRAME))
        self.skeleton, self.subset = body.skeleton, vertices
        if vertices is not None:
            self.rest_vertices = rest[vertices].detach().float().contiguous()
            self.bone_poses = rest["bone_poses"].detach().float()
        self._vertices: torch.Tensor | None = None
        self.transforms = torch.empty(0)
        self.chain, self.layout = body.skeleton.chain, body.anchored
        self.offsets = rest["offsets"].detach().float().contiguous()
        self.anchors = rest["local_anchors"].detach().float().contiguous()
        self.params = {name: params[name].detach().numpy()
                       for name in ("global_orient", "body_pose", "hand_pose")}
        self.transl = params["transl"].detach()  # shares the parameter's memory
        batch, bones = len(params["transl"]), self.chain.bones
        self.rotvecs = torch.empty(batch, 1 + params["body_pose"].shape[1]
                                   + params["hand_pose"].shape[1], 3)
        self.poses = torch.empty(batch, bones, 4, 4)
        self.keypoints = torch.empty(batch, len(self.layout.head), 3)
        self.pose_grad = torch.empty(batch, bones, 4, 4)
        self.anchor_grad = torch.empty(batch, *self.anchors.shape[1:])
        self.rotvec_grad, self.transl_grad = torch.empty_like(self.rotvecs), torch.empty(batch, 3)
        self.offset_grad = torch.empty(batch, *self.offsets.shape[1:])
        self.limits = body.limit_lo.numpy(), body.limit_hi.numpy()
        self.flexion = body.flexion_index.numpy()
        self._body_slots = slice(1, 1 + params["body_pose"].shape[1])

    def pose(self) -> torch.Tensor:
        rotvecs = self.rotvecs.numpy()
        rotvecs[:, 0] = self.params["global_orient"]
        rotvecs[:, self._body_slots] = self.params["body_pose"]
        rotvecs[:, self._body_slots.stop:] = self.params["hand_pose"]
        _POSE(len(rotvecs), self.rotvecs, self.transl, self.offsets, *self.chain.structure,
              self.poses)
        layout = self.layout
        _PLACE(self.keypoints.shape[:2], self.poses, self.anchors, layout.weight, layout.slot,
               layout.start, layout.pair, layout.head, self.keypoints)
        if self.subset is not None:
            self.transforms = self.skeleton.transforms(self.poses, self.bone_poses)[0]
            self._vertices = linear_blend_skinning(self.rest_vertices,
                                                   self.subset.data["binding"], self.transforms)
        return self.keypoints

    @property
    def vertices(self) -> torch.Tensor | None:
        return self._vertices

    def gradients(self, keypoint_grad: torch.Tensor, vertex_grad: torch.Tensor | None = None
                  ) -> dict[str, np.ndarray]:
        layout = self.layout
        for buffer in (self.pose_grad, self.anchor_grad, self.rotvec_grad, self.transl_grad,
                       self.offset_grad):
            buffer.numpy()[...] = 0
        _PLACE_GRAD(keypoint_grad.shape[:2], self.poses, self.anchors, layout.weight,
                    layout.slot, layout.start, layout.pair, layout.head, keypoint_grad,
                    self.pose_grad, self.anchor_grad)
        if vertex_grad is not None:
            self._add_skinning_gradients(vertex_grad)
        _POSE_GRAD(len(self.rotvecs), self.rotvecs, self.transl, self.offsets,
                   *self.chain.structure, self.poses, self.pose_grad, self.rotvec_grad,
                   self.transl_grad, self.offset_grad)
        rotvec = self.rotvec_grad.numpy()
        return {"global_orient": rotvec[:, 0], "body_pose": rotvec[:, self._body_slots],
                "hand_pose": rotvec[:, self._body_slots.stop:],
                "transl": self.transl_grad.numpy()}

    def _add_skinning_gradients(self, vertex_grad: torch.Tensor) -> None:
        """Add to the poses' gradient what the subset's vertices give, back through the
        skinning and its transforms (:meth:`AnnySkeleton.pose_gradient`)."""
        transform_grad, _ = skinning_gradients(self.rest_vertices, self.subset.data["binding"],
                                               self.transforms, vertex_grad)
        self.pose_grad += self.skeleton.pose_gradient(transform_grad, self.bone_poses)

    def priors(self) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
        pose, hands = self.params["body_pose"], self.params["hand_pose"]
        over = pose - np.clip(pose, *self.limits)
        bent = np.exp(-pose[:, self.flexion, 0])
        bending = np.zeros_like(pose)
        bending[:, self.flexion, 0] = -bent
        return {"pose_prior": ((pose ** 2).sum((1, 2)), {"body_pose": 2 * pose}),
                "joint_limits": ((over ** 2).sum((1, 2)), {"body_pose": 2 * over}),
                "bending": (bent.sum(1), {"body_pose": bending}),
                "hand_prior": ((hands ** 2).sum((1, 2)), {"hand_pose": 2 * hands})}
