"""A keypoint stage's objective worked out without autograd is the autograd objective: the
same rows' sums and gradients, under a tilted, rolled, off-centre camera, with and without
a previous frame's fit (sequence mode's temporal term)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from prox_engine.config import Stage, load_config
from prox_engine.fitting import Fitter
from prox_engine.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from prox_engine.keypoint_objective import KeypointObjective
from prox_engine.keypoints import ANKLES, FEET, KNEES

from .test_fitting import CAMERA, _posed_params, floor_scene, tilted_camera

FREE = ["transl", "global_orient", "body_pose", "hand_pose"]
# a keypoint stage with every prior, the shape's held, and the temporal term that a
# warm-started frame's has
STAGE = Stage("final", {"body": 1.0, "hands": 1.0, "pose_prior": 1.0, "bending": 3.0,
                        "hand_prior": 5.0, "shape": 3.0, "temporal": 300.0},
              optimize_shape=False, optimize_hands=True)


def _rows(body, cam2world: np.ndarray) -> tuple[dict[str, torch.Tensor], torch.Tensor,
                                                  torch.Tensor]:
    """Three bodies (standing, standing with both legs cut off at the knees, lying: the
    upright, plumb-shin and level terms each at work), their poses and shapes nudged, and
    keypoints off theirs by up to 40 px."""
    generator = torch.Generator().manual_seed(3)
    rows = [_posed_params(body, cam2world) for _ in range(3)]
    rotation = torch.tensor(cam2world[:3, :3], dtype=torch.float32)
    tip = torch.tensor(Rotation.from_euler("x", 85, degrees=True).as_matrix(),
                       dtype=torch.float32)  # about a world axis: the trunk 5 degrees off level
    rows[2]["global_orient"] = matrix_to_axis_angle(
        rotation.T @ tip @ rotation @ axis_angle_to_matrix(rows[2]["global_orient"]))
    params = {name: torch.cat([r[name] for r in rows]) for name in rows[0]}
    for name in ("global_orient", "body_pose", "hand_pose", "shape"):
        params[name] = params[name] + 0.1 * torch.randn(params[name].shape,
                                                        generator=generator)
    with torch.no_grad():
        keypoints = body(params, vertices=False).keypoints
    target = CAMERA.project(keypoints) + 40 * torch.rand(keypoints.shape[:2] + (2,),
                                                         generator=generator)
    conf = (0.3 + 0.7 * torch.rand(keypoints.shape[:2], generator=generator)
            ) * body.keypoint_mask
    conf[1, ANKLES] = 0
    conf[1, FEET] = 0
    conf[:, [1, 9, 12]] = 0  # as the fitter ignores them
    return params, target, conf


def _previous(body, params: dict[str, torch.Tensor]) -> torch.Tensor:
    """The keypoints of ``params``' bodies moved: every row's pose and root turned a
    little and shifted 10 cm, as a neighbouring frame's fit would be."""
    generator = torch.Generator().manual_seed(5)
    moved = {name: value.detach().clone() for name, value in params.items()}
    for name in ("global_orient", "body_pose"):
        moved[name] += 0.05 * torch.randn(moved[name].shape, generator=generator)
    moved["transl"] += torch.tensor([0.1, 0.0, 0.05])
    with torch.no_grad():
        return body(moved, vertices=False).keypoints


def _assert_autograd_agrees(rows: np.ndarray, grads: list[np.ndarray],
                            terms: dict[str, torch.Tensor], params: dict[str, torch.Tensor]
                            ) -> None:
    """The direct objective's row sums and gradients are autograd's, of the ``terms``."""
    total = torch.stack(list(terms.values())).sum(0)
    expected = torch.autograd.grad(total.sum(), [params[n] for n in FREE])
    np.testing.assert_allclose(rows, total.detach().numpy(), rtol=1e-5)
    for name, got, want in zip(FREE, grads, expected):
        assert got.shape == want.shape, name
        np.testing.assert_allclose(got, want.numpy(), rtol=1e-4,
                                   atol=1e-5 * float(want.abs().max()), err_msg=name)


@pytest.mark.parametrize("sequence", [False, True])
def test_the_direct_objective_is_the_autograd_objective(body, sequence):
    cam2world = tilted_camera()
    fitter = Fitter(body, CAMERA, load_config("prox"), floor_scene(cam2world))
    params, target, conf = _rows(body, cam2world)
    assert bool(conf[1, KNEES].gt(0).all())  # the second body's legs are cut off
    previous = _previous(body, params) if sequence else None
    for name in FREE:
        params[name].requires_grad_(True)
    direct = fitter._keypoint_objective(STAGE, params, FREE, target,
                                        fitter._held(STAGE, params, conf, FREE), previous)
    assert isinstance(direct, KeypointObjective)
    rows, grads = direct.evaluate()

    terms = fitter._terms(STAGE, params, target, conf, [None] * 3, previous, FREE)(
        body(params, vertices=False, spheres=False))
    assert ("temporal" in terms) == sequence
    for name in ("upright", "level", "plumb_shins", "shape", "hand_prior", "bending",
                 *(["temporal"] if sequence else [])):
        assert bool((terms[name] != 0).any()), name  # every term takes part
    _assert_autograd_agrees(rows, grads, terms, params)


def test_the_direct_scene_stage_is_the_autograd_scene_stage(body):
    """A warm-started frame's contact stage (the shape held, the scene terms on): the
    scene terms' vertices skinned by the keypoint path and their gradients taken back
    through the skinning give autograd's sums and gradients."""
    cam2world = tilted_camera()
    fitter = Fitter(body, CAMERA, load_config("prox"),
                    floor_scene(cam2world, height=0.05))  # the feet inside
    stage = Stage("contact", STAGE.weights | {"penetration": 3000.0, "contact": 300.0},
                  optimize_shape=False, optimize_hands=True)
    params, target, conf = _rows(body, cam2world)
    previous = _previous(body, params)
    for name in FREE:
        params[name].requires_grad_(True)
    direct = fitter._keypoint_objective(stage, params, FREE, target,
                                        fitter._held(stage, params, conf, FREE), previous)
    assert isinstance(direct, KeypointObjective) and direct.mesh is not None
    rows, grads = direct.evaluate()

    terms = fitter._terms(stage, params, target, conf, [None] * 3, previous, FREE)(
        body(params, vertices=fitter.scene_subset, spheres=False))
    for name in ("penetration", "contact"):
        assert bool((terms[name] != 0).any()), name  # the standing bodies meet it
    _assert_autograd_agrees(rows, grads, terms, params)


@pytest.mark.parametrize("term", ["self_penetration", "depth", "shape free"])
def test_stages_that_read_more_than_keypoints_pose_and_scene_terms_go_through_autograd(
        body, term):
    """The whole mesh, the collision spheres or a free shape: autograd."""
    cam2world = tilted_camera()
    fitter = Fitter(body, CAMERA, load_config("prox"), floor_scene(cam2world))
    params, target, conf = _rows(body, cam2world)
    free = [*FREE, "shape"] if term == "shape free" else FREE
    weights = dict(STAGE.weights) | ({"penetration": 1.0} if term == "shape free"
                                     else {term: 1.0})
    stage = Stage("s", weights)
    assert fitter._keypoint_objective(stage, params, free, target,
                                      fitter._held(stage, params, conf, free), None) is None
    assert fitter._keypoint_objective(STAGE, params, FREE, target,
                                      fitter._held(STAGE, params, conf, FREE), None) is not None
