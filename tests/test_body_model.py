"""The anny backend honours the body-model interface."""
from __future__ import annotations

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
