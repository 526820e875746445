"""Forward kinematics of anny's skeleton for the fitted rotations, as batched 3x3 and 4x4
matrix products: anny's own (``get_bone_transforms``, 'local-bone') builds every bone's 4x4
delta matrix and multiplies by broadcast sums, about twice the operations, which on a CPU
cost more than the arithmetic (a body evaluation is thousands of tiny operations).

In anny's notation (``anny.utils.kinematics.forward_kinematic``): bone c of parent p has
rest pose P_c = [R_c | h_c], fixed reference orientation U_c and fitted rotation D_c.
Its posed pose is W_c = W_p K_c with K_c = [U_p^T U_c D_c | R_p^T (h_c - h_p)] (the root's
children: [.. | U_0^T (h_c - h_0)]), W_0 = [D_0 | transl], and its skinning transform is
T_c = W_c P_c^-1.

The chain W_c = K_0 K_1 ... K_c is composed level by level (16 rounds of one gather and
one product over the level's bones), or, for a few bodies, by pointer jumping: each round
multiplies every bone's product so far by that of the bone as many levels above it, so
the 17 levels take 5 rounds over all bones. A round's cost is its dispatch for a few
bodies (2 bodies: 2.3 -> 1.8 ms forward and backward) but its products for many (16: 3.8
-> 4.8 ms).

The chain's gradient is written out (:class:`_Chain`) instead of left to autograd, which
would retrace every round: since W_d = W_c (W_c^-1 W_d) for every bone d below c, the
loss's gradient in W_c, the others' local poses held, is (sum over d in c's subtree of
G_d W_d^T) W_c^-T, with G the gradient in the posed poses: one product with a constant
ancestor matrix for the sums, then one in each local pose K_c = W_p^-1 W_c (values and
gradients as anny's, tests/test_body_model.py).
"""
from __future__ import annotations

import torch

from ..geometry import axis_angle_to_matrix

JUMP_BATCH = 4  # pointer jumping up to this many bodies


class AnnySkeleton(torch.nn.Module):
    """The bone chain of an anny model whose rotations are the root, ``posed`` bones (in
    the order their axis-angles come) and identity for the rest."""

    def __init__(self, model: torch.nn.Module, posed: torch.Tensor) -> None:
        super().__init__()
        self.levels = model.kinematic_chain_levels  # (first, last) of each depth level
        local, order, inverse, parent = model.kinematic_chain_indices
        count = len(order)
        reference = model.reference_bone_orientations
        slot = torch.full((count,), 1 + len(posed), dtype=torch.long)  # identity
        slot[0] = 0
        slot[posed] = 1 + torch.arange(len(posed))
        self.register_buffer("local", local)  # parent's position in the level before
        self.register_buffer("order", order)  # bones in depth order
        self.register_buffer("inverse", inverse)
        self.register_buffer("parent", parent)
        self.register_buffer("slot", slot[order])  # each bone's rotation, depth order
        turn = (reference[parent].transpose(-1, -2) @ reference)[order]  # U_p^T U_c
        turn[0] = torch.eye(3)  # the root's local rotation is D_0 itself
        self.register_buffer("turn", turn)  # depth order
        self.register_buffer("root_reference", reference[0])
        self.register_buffer("bottom", torch.tensor([0.0, 0.0, 0.0, 1.0]))
        self.register_buffer("identity", torch.eye(3))  # the unposed bones' rotation
        # Pointer jumping's rounds, in depth order: each bone's "bone above" is its parent,
        # then the bone 2, 4, 8, ... levels up; above the root is the index ``count``, an
        # identity matrix.
        above = torch.cat([inverse[parent[order]], torch.tensor([count])])
        above[0] = count
        jumps = []
        while bool((above[:count] < count).any()):
            jumps.append(above)
            above = above[above]
        self.register_buffer("jumps", torch.stack(jumps))  # (rounds, count + 1)
        self.register_buffer("above_root", torch.eye(4))
        # Each bone's subtree (itself and every bone below it), depth order, for _Chain's
        # gradient.
        subtree, bone, up = torch.eye(count), torch.arange(count), jumps[0]
        while bool((up[bone] < count).any()):
            bone = torch.where(up[bone] < count, up[bone], bone)  # the root stays put
            subtree[bone, torch.arange(count)] = 1.0
        self.register_buffer("subtree", subtree)

    def offsets(self, rest_poses: torch.Tensor) -> torch.Tensor:
        """(B, J, 3) each bone's head from its parent's in the parent's frame, depth order;
        depends on the shape only."""
        rotation, head = rest_poses[..., :3, :3], rest_poses[..., :3, 3]
        step = (head - head[:, self.parent])[..., None]
        offset = torch.where((self.parent == 0)[:, None, None], self.root_reference.T @ step,
                             rotation[:, self.parent].transpose(-1, -2) @ step)[..., 0]
        return offset[:, self.order]

    def forward(self, rotvecs: torch.Tensor, transl: torch.Tensor, rest_poses: torch.Tensor,
                offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Skinning transforms T and posed poses W (B, J, 4, 4) for axis-angles ``rotvecs``
        (B, 1 + len(posed), 3), the root's first, the root at ``transl`` (B, 3), of the
        body whose rest poses are ``rest_poses`` (B or 1, J, 4, 4), with their
        :meth:`offsets`."""
        batch = len(rotvecs)
        rotations = axis_angle_to_matrix(rotvecs)
        rotations = torch.cat([rotations, self.identity.expand(batch, 1, 3, 3)], 1)[:, self.slot]
        shifts = torch.cat([transl[:, None], offsets.expand(batch, -1, -1)[:, 1:]], 1)
        poses = _Chain.apply(rotations, shifts, self)
        poses = poses[:, self.inverse]
        rest_rotation, rest_head = rest_poses[..., :3, :3], rest_poses[..., :3, 3]
        rotation = poses[..., :3, :3] @ rest_rotation.transpose(-1, -2)
        shift = poses[..., :3, 3] - (rotation @ rest_head[..., None])[..., 0]
        bottom = self.bottom.expand(batch, len(self.slot), 1, 4)
        transforms = torch.cat([torch.cat([rotation, shift[..., None]], -1), bottom], -2)
        return transforms, poses

    def chain(self, local: torch.Tensor) -> torch.Tensor:
        """Posed poses W (B, J, 4, 4), depth order, of the local poses K (B, J, 4, 4)."""
        batch = len(local)
        if batch <= JUMP_BATCH:
            poses = torch.cat([local, self.above_root.expand(batch, 1, 4, 4)], 1)
            for above in self.jumps:
                poses = poses.index_select(1, above) @ poses
            return poses[:, :-1]
        chain = [local[:, :1]]
        for first, last in self.levels[1:]:
            chain.append(chain[-1][:, self.local[first:last]] @ local[:, first:last])
        return torch.cat(chain, 1)


class _Chain(torch.autograd.Function):
    """Posed poses W (B, J, 4, 4), depth order, from local rotations D (B, J, 3, 3) and
    translations (B, J, 3) (the root's: ``transl``; the others': offsets), with the
    gradient of the module docstring."""

    @staticmethod
    def forward(ctx, rotations: torch.Tensor, shifts: torch.Tensor,
                skeleton: AnnySkeleton) -> torch.Tensor:
        bottom = skeleton.bottom.expand(*rotations.shape[:2], 1, 4)
        local = torch.cat([torch.cat([skeleton.turn @ rotations, shifts[..., None]],
                                     -1), bottom], -2)
        poses = skeleton.chain(local)
        ctx.save_for_backward(poses)
        ctx.skeleton = skeleton
        return poses

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None]:
        poses, = ctx.saved_tensors
        skeleton = ctx.skeleton
        batch, count = poses.shape[:2]
        sums = skeleton.subtree @ (grad @ poses.transpose(-1, -2)).reshape(batch, count, 16)
        rotation, head = poses[..., :3, :3], poses[..., :3, 3:]
        inverse_t = torch.cat([torch.cat([rotation, torch.zeros_like(head)], -1),
                               torch.cat([-(rotation.transpose(-1, -2) @ head).transpose(-1, -2),
                                          head.new_ones(batch, count, 1, 1)], -1)], -2)
        parents = torch.cat([poses, skeleton.above_root.expand(batch, 1, 4, 4)], 1)[
            :, skeleton.jumps[0, :count]]
        local = parents.transpose(-1, -2) @ sums.view(batch, count, 4, 4) @ inverse_t
        return (skeleton.turn.transpose(-1, -2) @ local[..., :3, :3],
                local[..., :3, 3], None)
