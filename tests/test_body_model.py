"""The anny backend honours the body-model interface."""
from __future__ import annotations

from contextlib import nullcontext

import pytest
import torch

from prox_engine.body.anny_body import BODY_BONES
from prox_engine.losses import self_penetration


def test_anny_topology_and_outputs(body):
    params = body.init_params(2)
    out = body(params)
    assert out.vertices.shape == (2, 13718, 3) and body.faces.shape == (27420, 3)
    assert out.keypoints.shape == (2, 118, 3)
    assert int(body.scene_vertices.sum()) == 13348  # eyes and tongue excluded
    for part in ("left_hand", "right_hand", "left_foot", "right_foot", "back", "gluteus",
                 "thighs"):
        assert len(body.contact_parts[part]) > 20, part
    kp = out.keypoints[0]
    assert kp[5, 0] > kp[2, 0]  # left shoulder on the model's +x side
    assert kp[0, 2] > kp[1, 2] > kp[8, 2] > kp[11, 2]  # nose, neck, mid-hip, ankle downwards


def test_keypoints_without_the_mesh_are_the_regressed_skinned_vertices(body):
    """The fitting stages pose keypoints from per-bone anchors instead of skinning 13718
    vertices: the same points as the vertex regressor (and fingertip vertices) on the posed,
    reshaped mesh, with the same gradients."""
    from prox_engine.keypoints import BODY, LEFT_HAND, RIGHT_HAND

    torch.manual_seed(3)
    params = body.init_params(3)
    params["body_pose"] += torch.randn_like(params["body_pose"]) * 0.4
    params["hand_pose"] += torch.randn_like(params["hand_pose"]) * 0.3
    params["global_orient"] = torch.randn(3, 3)
    params["transl"] = torch.randn(3, 3)
    params["shape"] = params["shape"] + torch.randn_like(params["shape"])
    grads = []
    for mesh in (True, False):
        leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
        out = body(leaves, vertices=mesh)
        assert (out.vertices is None) != mesh
        body_points = out.keypoints[:, BODY]
        if mesh:  # the vertex regressor applied to the skinned mesh
            regressed = torch.einsum("kv,bvd->bkd", body.keypoint_weights, out.vertices)
            assert torch.allclose(body_points, regressed, atol=1e-4)
            tips = torch.cat([out.keypoints[:, LEFT_HAND][:, 4::4],
                              out.keypoints[:, RIGHT_HAND][:, 4::4]], 1)
            assert torch.allclose(tips, out.vertices[:, body.fingertips], atol=1e-5)
            with_mesh, body_points = out.keypoints.detach(), regressed
        else:
            assert torch.allclose(out.keypoints, with_mesh, atol=1e-6)
        (body_points ** 2).sum().backward()
        grads.append(torch.cat([leaves[k].grad.flatten() for k in sorted(leaves)
                                if leaves[k].grad is not None]))
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4)


def test_a_vertex_subset_is_posed_as_the_whole_mesh_picks_it(body):
    """Posing a subset (in any order, repeated ids once) gives the whole mesh's vertices
    at those ids, in ascending order, with the same gradients, the shape free or frozen."""
    torch.manual_seed(4)
    params = body.init_params(2)
    params["body_pose"] += torch.randn_like(params["body_pose"]) * 0.4
    params["global_orient"] = torch.randn(2, 3)
    params["transl"] = torch.randn(2, 3)
    params["shape"] = params["shape"] + torch.randn_like(params["shape"])
    subset = body.vertex_subset(torch.tensor([9000, 17, 4000, 17, 13000]))
    assert subset.ids.tolist() == [17, 4000, 9000, 13000]
    weights = torch.randn(2, 4, 3)
    for free_shape in (True, False):
        grads, posed = [], []
        for request in (True, subset):
            leaves = {k: v.clone().requires_grad_(k != "shape" or free_shape)
                      for k, v in params.items()}
            vertices = body(leaves, vertices=request).vertices
            vertices = vertices[:, subset.ids] if request is True else vertices
            assert vertices.shape == (2, 4, 3)
            (vertices * weights).sum().backward()
            posed.append(vertices.detach())
            grads.append(torch.cat([leaves[k].grad.flatten() for k in sorted(leaves)
                                    if leaves[k].grad is not None]))
        assert torch.allclose(posed[0], posed[1], atol=1e-6)
        assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4)


def test_a_shape_expansion_is_first_order_about_its_point_and_exact_outside(body):
    """Within :meth:`shape_expanded` a free shape's vertices, keypoints and their
    gradients are the first-order expansion about each row's own expansion point: equal
    to the model's at the point (gradients within 1e-4: the slopes are central
    differences in float32), within 0.1 mm (gradients within 3 %) a scene stage's step
    away (0.05 logits; 0.2 mm in a batch of 8 other shapes), apart by second-order terms at
    0.3; a frozen shape, another vertex subset and the model outside the context are
    exact."""
    torch.manual_seed(5)
    params = body.init_params(2)
    params["body_pose"] += torch.randn_like(params["body_pose"]) * 0.3
    params["shape"] = params["shape"] + torch.randn_like(params["shape"]) * 0.5
    subset = body.vertex_subset(torch.nonzero(body.scene_vertices).flatten())
    direction = torch.tensor([[1.0, -1, 1, -1, 1, -1], [-1.0, 1, 1, -1, -1, 1]])

    def posed(step: float, expand: bool, free: bool = True, request=subset):
        leaves = {k: v.clone() for k, v in params.items()}
        with body.shape_expanded(leaves, subset) if expand else nullcontext():
            leaves["shape"] += step * direction  # in place, as the optimiser steps
            out = body({**leaves, "shape": leaves["shape"].requires_grad_(free)},
                       vertices=request)
        if not free:
            return out.vertices, out.keypoints, None
        (out.vertices.square().sum() + out.keypoints.square().sum()).backward()
        return out.vertices.detach(), out.keypoints.detach(), leaves["shape"].grad

    def apart(a, b) -> float:
        return float((a - b).norm(dim=-1).max())

    for step, bound in ((0.0, 1e-6), (0.05, 1e-4)):
        expanded, exact = posed(step, True), posed(step, False)
        assert apart(expanded[0], exact[0]) < bound
        assert apart(expanded[1], exact[1]) < bound
        gap = float((expanded[2] - exact[2]).norm() / exact[2].norm())
        assert gap < (1e-4 if step == 0 else 0.03)  # the slope moves with the point
    far = apart(posed(0.3, True)[0], posed(0.3, False)[0])
    assert 1e-3 < far < 1e-2  # the expansion, not the model: second order shows at 0.3
    assert apart(posed(0.3, True, free=False)[0], posed(0.3, False, free=False)[0]) < 1e-6
    whole = body.vertex_subset(torch.arange(body.num_vertices))
    assert apart(posed(0.3, True, request=whole)[0], posed(0.3, False, request=whole)[0]) < 1e-6
    after = posed(0.3, False)
    with body.shape_expanded(params, subset):
        pass
    assert apart(posed(0.3, False)[0], after[0]) < 1e-6
    batch = {k: v.repeat(4, *[1] * (v.dim() - 1)) for k, v in params.items()}
    batch["shape"] = batch["shape"] + torch.randn_like(batch["shape"]) * 0.5
    with body.shape_expanded(batch, subset):
        moved = {**batch, "shape": (batch["shape"] + 0.05 * direction.repeat(4, 1)
                                    ).requires_grad_(True)}
        expanded = body(moved, vertices=subset).vertices
    assert apart(expanded, body(moved, vertices=subset).vertices) < 2e-4


def test_translation_and_orientation(body):
    params = body.init_params(1)
    base = body(params).vertices
    params["transl"][0] = torch.tensor([0.1, -0.2, 3.0])
    moved = body(params).vertices
    assert torch.allclose(moved - base, torch.tensor([0.1, -0.2, 3.0]).expand_as(base), atol=1e-5)


def test_priors_penalise_implausible_poses(body):
    params = body.init_params(1)
    assert body.pose_prior(params).item() == 0
    knee = BODY_BONES.index("lowerleg01.L")
    bent = {k: v.clone() for k, v in params.items()}
    bent["body_pose"][0, knee, 0] = 1.2
    wrong = {k: v.clone() for k, v in params.items()}
    wrong["body_pose"][0, knee, 0] = -1.2
    assert body.joint_limits(wrong) > 1 and body.joint_limits(bent) == 0
    assert body.bending_prior(wrong) > body.bending_prior(bent)
    adult = body.shape_prior(params)
    child = {k: v.clone() for k, v in params.items()}
    child["shape"][0, 1] = -2.0  # young age
    assert body.shape_prior(child) > adult + 10


def test_self_penetration_detects_arm_in_torso(body):
    params = body.init_params(1)
    assert self_penetration(body(params), body).item() == 0
    params["body_pose"][0, BODY_BONES.index("upperarm01.L"), 2] = -1.4  # arm into the chest
    params["body_pose"][0, BODY_BONES.index("upperarm01.L"), 0] = 0.6
    assert self_penetration(body(params), body).item() > 0


def test_relative_size_is_one_for_the_mean_body_and_grows_with_height(body):
    """A body's size over the prior-mean body's: exactly 1 for the mean shape (however
    posed), above 1 for a taller shape, below for a shorter one, as its standing mesh's
    height (anny measures its rest skeleton's, without posing a mesh)."""
    params = body.init_params(3, "sitting")
    assert torch.equal(body.relative_size(params), torch.ones(3))
    height = 4  # the shape logits' height
    params["shape"][1, height] += 1.0
    params["shape"][2, height] -= 1.0
    sizes = body.relative_size(params)
    standing = body.init_params(3)
    standing["shape"] = params["shape"]
    with torch.no_grad():
        vertices = body(standing).vertices
    up = body.up_axis()
    heights = (vertices @ up).max(1).values - (vertices @ up).min(1).values
    assert float(sizes[1]) > 1.03 and float(sizes[2]) < 0.97, sizes
    assert torch.allclose(sizes, heights / heights[0], atol=0.01), (sizes, heights)


def test_stature_is_the_standing_height_the_benchmark_gives_its_people(body):
    """A body's stature is its standing mesh's height by its shape alone, however it is
    posed: the measure the benchmark's generator records for its people
    (benchmarks.poses.stature), which the benchmark's size ratio compares a fit's with."""
    from benchmarks.poses import stature
    from prox_engine.body.anny_body import PHENOTYPES

    tall = {"gender": 0.1, "age": float(torch.sigmoid(body.shape_init[0, 1])),
            "muscle": 0.5, "weight": 0.6, "height": 0.55, "proportions": 0.4}
    params = body.init_params(2, "kneeling")
    params["shape"][1] = torch.logit(torch.tensor([tall[k] for k in PHENOTYPES]))
    statures = body.stature(params)
    mean = dict(zip(PHENOTYPES, torch.sigmoid(body.shape_init[0]).tolist()))
    assert float(statures[0]) == pytest.approx(stature(body, mean), abs=2e-3)
    assert float(statures[1]) == pytest.approx(stature(body, tall), abs=2e-3)
    assert float(statures[1]) > float(statures[0]) + 0.05


def test_shape_prior_is_annys_age_conditioned_beta_likelihood(body):
    """The one-table shape prior equals anny's own sixteen Beta distributions, values and
    gradients, across genders and ages (including ages between and beyond their anchors)."""
    torch.manual_seed(0)
    shape = (torch.randn(32, 6) * 1.5).requires_grad_(True)
    p = torch.sigmoid(shape).clamp(1e-3, 1 - 1e-3)
    gender, age = p[:, 0], p[:, 1]
    expected = ((age - body.prior_age) / 0.05) ** 2 / 2
    for column, name in ((4, "height"), (3, "weight"), (2, "muscle"), (5, "proportions")):
        for who, share in (("boys", 1 - gender), ("girls", gender)):
            dist = getattr(body.shape_distribution, f"{who}_conditional_{name}_distribution")
            expected = expected - share * dist.get_torch_distribution(age).log_prob(p[:, column])
    ours = body.shape_prior({"shape": shape})
    torch.testing.assert_close(ours, expected.float(), rtol=1e-4, atol=1e-4)
    grad_ours, = torch.autograd.grad(ours.sum(), shape)
    grad_expected, = torch.autograd.grad(expected.sum(), shape)
    torch.testing.assert_close(grad_ours, grad_expected.float(), rtol=1e-3, atol=1e-3)


def test_phenotype_coefficients_are_annys(body):
    """The one-gather blendshape coefficients equal anny's own, values and gradients, over
    random phenotypes and the anchors' ends (where anny clamps)."""
    torch.manual_seed(2)
    phenotype = torch.cat([torch.rand(64, 6), torch.tensor([[0.0] * 6, [1.0] * 6])])
    phenotype.requires_grad_(True)
    empty = phenotype.new_zeros(len(phenotype), 0)
    theirs = body.model._get_phenotype_blendshape_coefficients(phenotype, empty, empty)
    ours = body.phenotype_coefficients(phenotype)
    torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-6)
    weights = torch.randn_like(theirs)
    grad_ours, = torch.autograd.grad((ours * weights).sum(), phenotype)
    grad_theirs, = torch.autograd.grad((theirs * weights).sum(), phenotype)
    torch.testing.assert_close(grad_ours[:64], grad_theirs[:64], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("batch", [1, 6])
def test_forward_kinematics_are_annys(body, batch):
    """The skeleton's bone chain (a warp kernel each way) gives anny's own bone transforms
    and posed bone poses ('local-bone'), values and gradients, for reshaped, posed
    bodies, one or a batch."""
    from prox_engine.geometry import axis_angle_to_matrix

    torch.manual_seed(4)
    params = body.init_params(batch, "sitting")
    for name in ("global_orient", "body_pose", "hand_pose", "transl"):
        params[name] = params[name] + torch.randn_like(params[name]) * 0.5
    params["shape"] = params["shape"] + torch.randn_like(params["shape"])
    leaves = {k: v.requires_grad_(True) for k, v in params.items()}
    rest = body._rest(leaves["shape"], vertices=False)
    delta = torch.eye(4).repeat(batch, len(body.bone_labels), 1, 1)
    delta[:, 0, :3, :3] = axis_angle_to_matrix(leaves["global_orient"])
    delta[:, 0, :3, 3] = leaves["transl"]
    delta[:, body.body_index, :3, :3] = axis_angle_to_matrix(leaves["body_pose"])
    delta[:, body.hand_index, :3, :3] = axis_angle_to_matrix(leaves["hand_pose"])
    theirs = body.model.get_bone_transforms(delta, rest["bone_poses"])
    rotvecs = torch.cat([leaves["global_orient"][:, None], leaves["body_pose"],
                         leaves["hand_pose"]], 1)
    ours = body.skeleton.transforms(body.skeleton.pose(rotvecs, leaves["transl"],
                                                       rest["offsets"]), rest["bone_poses"])
    weights = [torch.randn_like(t) for t in theirs]
    grads = []
    for result in (theirs, ours):
        for mine, reference in zip(result, theirs):
            torch.testing.assert_close(mine, reference, rtol=1e-5, atol=1e-5)
        loss = sum((t * w).sum() for t, w in zip(result, weights))
        grads.append(torch.autograd.grad(loss, list(leaves.values()), retain_graph=True))
    for mine, reference in zip(grads[1], grads[0]):
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-4)


def test_loading_the_body_model_prints_nothing():
    """No warp device banner or CUDA warning at the head of every command and worker log
    (the warning comes from warp's C code, straight to file descriptor 2)."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", "from prox_engine.body.anny_body import "
                          "AnnyBody; AnnyBody.load()"], capture_output=True, text=True,
                         check=True)
    assert run.stdout == "" and "Warp" not in run.stderr, run.stderr


def test_bone_chain_shares_one_set_of_offsets_and_handles_tiny_angles(body):
    """Bodies posed with one set of offsets get the same poses as with a copy each, and
    the offsets' gradient is the sum of theirs; near-zero and small axis-angles (the
    series branches) differentiate as torch's Rodrigues does."""
    from prox_engine.geometry import axis_angle_to_matrix

    torch.manual_seed(5)
    chain = body.skeleton.chain
    rotvecs = torch.randn(3, 72, 3) * 0.5
    rotvecs[:, 1] = 1e-6 * torch.randn(3)
    rotvecs[:, 2] = 0.05 * torch.randn(3)
    rotvecs.requires_grad_(True)
    transl = torch.randn(3, 3).requires_grad_(True)
    rest = body._rest(body.init_params(1)["shape"], None)
    shared = rest["offsets"].detach().clone().requires_grad_(True)
    copies = shared.detach().repeat(3, 1, 1).requires_grad_(True)
    weights = torch.randn(3, shared.shape[1], 4, 4)
    one, each = chain(rotvecs, transl, shared), chain(rotvecs, transl, copies)
    assert torch.equal(one, each)
    grad_shared, = torch.autograd.grad((one * weights).sum(), shared)
    grad_copies, = torch.autograd.grad((each * weights).sum(), copies)
    torch.testing.assert_close(grad_shared, grad_copies.sum(0, keepdim=True))
    # The root's pose is [R(a) | transl]: for a large, a small and a near-zero angle (the
    # series branches), its rotation and gradient are torch's Rodrigues'.
    for k in range(3):
        angle = rotvecs.detach()[:, k].clone().requires_grad_(True)
        posed = torch.cat([angle[:, None], rotvecs.detach()[:, 1:]], 1)
        root = chain(posed, transl.detach(), shared.detach())[:, 0, :3, :3]
        torch.testing.assert_close(root, axis_angle_to_matrix(angle))
        g = torch.randn(3, 3, 3)
        ours, = torch.autograd.grad((root * g).sum(), angle)
        theirs, = torch.autograd.grad((axis_angle_to_matrix(angle) * g).sum(), angle)
        torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("shared", [False, True])
def test_skinning_is_annys(body, shared):
    """Skinning that skips a vertex's empty bone slots poses and differentiates as anny's
    kernel, for a batch of bodies with rest vertices of their own or one set for all; with
    the rest vertices held, the bones' gradient is the same to the bit."""
    from anny.skinning import warp_skinning

    from prox_engine.body.skinning import Binding, linear_blend_skinning

    torch.manual_seed(6)
    data = {"template": body.model.template_vertices,
            "weights": body.model.vertex_bone_weights, "indices": body.model.vertex_bone_indices}
    count = 1 if shared else 3
    rest = (data["template"] + 0.01 * torch.randn(count, *data["template"].shape))
    rest.requires_grad_(True)
    transforms = torch.eye(4).repeat(3, len(body.bone_labels), 1, 1)
    transforms[:, :, :3] += 0.2 * torch.randn(3, len(body.bone_labels), 3, 4)
    transforms.requires_grad_(True)
    binding = Binding(data["weights"], data["indices"])
    ours = linear_blend_skinning(rest, binding, transforms)
    theirs = warp_skinning.linear_blend_skinning(rest.expand(3, -1, -1), data["weights"],
                                                 data["indices"], transforms)
    torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)
    weights = torch.randn_like(ours)
    grads = [torch.autograd.grad((posed * weights).sum(), [rest, transforms])
             for posed in (ours, theirs)]
    for mine, reference in zip(*grads):
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-4)
    held = linear_blend_skinning(rest.detach(), binding, transforms)
    bones, = torch.autograd.grad((held * weights).sum(), [transforms])
    assert torch.equal(bones, grads[0][1])


@pytest.mark.parametrize("shared", [False, True])
def test_anchored_points_are_the_torch_composition(body, shared):
    """The anchored-points kernels against the torch gather, product, scatter-add and
    gather they replace, on random (non-rigid) poses: the points, and the gradients of the
    poses and anchors (one set of anchors for both bodies, or one each), hand heads and the
    face's zeros included."""
    generator = torch.Generator().manual_seed(7)
    poses = torch.randn(2, len(body.skeleton.inverse), 4, 4, generator=generator)
    anchors = torch.randn(1 if shared else 2, len(body.anchor_point), 3, generator=generator)
    poses.requires_grad_(True)
    anchors.requires_grad_(True)

    def torch_points(poses, anchors):
        held = poses[:, body.anchor_slot, :3]
        moved = ((held[..., :3] @ anchors.expand(2, -1, -1)[..., None])[..., 0]
                 + held[..., 3] * body.anchor_weight[:, None])
        rows = len(body.keypoint_weights) + len(body.fingertips)
        points = moved.new_zeros(2, rows, 3).index_add(1, body.anchor_point, moved)
        return torch.cat([points, poses[:, body.hand_head_slot, :3, 3],
                          points.new_zeros(2, 1, 3)], 1)[:, body.keypoint_source]

    ours, theirs = body.anchored(poses, anchors), torch_points(poses, anchors)
    assert torch.allclose(ours, theirs, atol=1e-5)
    mix = torch.randn(ours.shape, generator=generator)
    expected = torch.autograd.grad((theirs * mix).sum(), [poses, anchors])
    for got, want in zip(torch.autograd.grad((ours * mix).sum(), [poses, anchors]), expected):
        assert got.shape == want.shape and torch.allclose(got, want, atol=1e-4)


def test_joint_limits_and_their_gradient_are_the_squared_excess(body):
    """The joint limits computed with their gradient equal the relu form autograd
    differentiates, on poses inside, above and below the limits."""
    from prox_engine.body.base import limit_excess

    generator = torch.Generator().manual_seed(4)
    pose = (torch.randn(3, *body.limit_lo.shape, generator=generator) * 1.5).requires_grad_()
    ours = limit_excess(pose, body.limit_lo, body.limit_hi)
    theirs = ((torch.relu(pose - body.limit_hi) + torch.relu(body.limit_lo - pose)) ** 2
              ).sum((1, 2))
    assert torch.equal(ours, theirs) and bool((ours > 0).all())
    mix = torch.tensor([1.0, -2.0, 0.5])
    (got,) = torch.autograd.grad((ours * mix).sum(), pose)
    (want,) = torch.autograd.grad((theirs * mix).sum(), pose)
    assert torch.allclose(got, want) and bool((got == 0).any())
