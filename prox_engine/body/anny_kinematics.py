"""Forward kinematics of anny's skeleton for the fitted rotations: the bone chain in one
warp kernel (:mod:`.bone_chain`), the skinning transforms by batched 3x3 products. anny's own
(``get_bone_transforms``, 'local-bone') builds every bone's 4x4 delta matrix and multiplies
by broadcast sums, and a torch chain composed level by level still made the skeleton's
forward and backward pass 803 small operations (181 now), which on a CPU cost more than the
arithmetic.

In anny's notation (``anny.utils.kinematics.forward_kinematic``): bone c of parent p has
rest pose P_c = [R_c | h_c], fixed reference orientation U_c and fitted rotation D_c.
Its posed pose is W_c = W_p K_c with K_c = [U_p^T U_c D_c | R_p^T (h_c - h_p)] (the root's
children: [.. | U_0^T (h_c - h_0)]), W_0 = [D_0 | transl], and its skinning transform is
T_c = W_c P_c^-1 (values and gradients as anny's, tests/test_body_model.py).
"""
from __future__ import annotations

import torch

from .bone_chain import BoneChain


class AnnySkeleton(torch.nn.Module):
    """The bone chain of an anny model whose rotations are the root, ``posed`` bones (in
    the order their axis-angles come) and identity for the rest."""

    def __init__(self, model: torch.nn.Module, posed: torch.Tensor) -> None:
        super().__init__()
        _, order, inverse, parent = model.kinematic_chain_indices
        count = len(order)
        reference = model.reference_bone_orientations
        slot = torch.full((count,), 1 + len(posed), dtype=torch.long)  # identity
        slot[0] = 0
        slot[posed] = 1 + torch.arange(len(posed))
        self.register_buffer("order", order)  # bones in depth order
        self.register_buffer("inverse", inverse)
        self.register_buffer("parent", parent)
        turn = (reference[parent].transpose(-1, -2) @ reference)[order]  # U_p^T U_c
        turn[0] = torch.eye(3)  # the root's local rotation is D_0 itself
        self.register_buffer("root_reference", reference[0])
        self.register_buffer("bottom", torch.tensor([0.0, 0.0, 0.0, 1.0]))
        above = inverse[parent[order]]  # each bone's parent, depth order; the root: count
        above[0] = count
        self.chain = BoneChain(slot[order], turn, above)

    def offsets(self, rest_poses: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) each bone's head from its parent's in the parent's frame, depth order;
        depends on the shape only."""
        rotation, head = rest_poses[..., :3, :3], rest_poses[..., :3, 3]
        step = (head - head[:, self.parent])[..., None]
        offset = torch.where((self.parent == 0)[:, None, None], self.root_reference.T @ step,
                             rotation[:, self.parent].transpose(-1, -2) @ step)[..., 0]
        return offset[:, self.order]

    def pose(self, rotvecs: torch.Tensor, transl: torch.Tensor, offsets: torch.Tensor
             ) -> torch.Tensor:
        """Posed poses W (B, J, 4, 4) in depth order (bone j's at ``inverse[j]``) for
        axis-angles ``rotvecs`` (B, 1 + len(posed), 3), the root's first, the root at
        ``transl`` (B, 3), of the body whose rest poses have these :meth:`offsets`."""
        return self.chain(rotvecs, transl, offsets)

    def transforms(self, poses: torch.Tensor, rest_poses: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Skinning transforms T and posed poses W (B, J, 4, 4), in bone order, of the
        depth-ordered :meth:`pose` ``poses`` of the body whose rest poses are
        ``rest_poses`` (B or 1, J, 4, 4)."""
        batch = len(poses)
        poses = poses[:, self.inverse]
        rest_rotation, rest_head = rest_poses[..., :3, :3], rest_poses[..., :3, 3]
        rotation = poses[..., :3, :3] @ rest_rotation.transpose(-1, -2)
        shift = poses[..., :3, 3] - (rotation @ rest_head[..., None])[..., 0]
        bottom = self.bottom.expand(batch, poses.shape[1], 1, 4)
        transforms = torch.cat([torch.cat([rotation, shift[..., None]], -1), bottom], -2)
        return transforms, poses

    def pose_gradient(self, transform_grad: torch.Tensor, rest_poses: torch.Tensor
                      ) -> torch.Tensor:
        """The gradient (B, J, 4, 4, depth order, the bottom rows 0) in the :meth:`pose`
        poses [R | t] of a loss whose gradient in their :meth:`transforms` (bone order) is
        ``transform_grad``: T = [R R0^T | t - R R0^T h0], the rest poses [R0 | h0] being
        ``rest_poses`` (B or 1, J, 4, 4)."""
        rotation_grad, shift_grad = transform_grad[..., :3, :3], transform_grad[..., :3, 3]
        rest_rotation, rest_head = rest_poses[..., :3, :3], rest_poses[..., :3, 3]
        grad = torch.zeros_like(transform_grad)
        grad[..., :3, :3] = (rotation_grad
                             - shift_grad[..., :, None] * rest_head[..., None, :]) @ rest_rotation
        grad[..., :3, 3] = shift_grad
        return grad[:, self.order]
