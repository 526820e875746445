"""The annealed PROX optimisation: initialisation, camera stage, weighted stages (L-BFGS
with strong Wolfe line search), for a batch of frames or warm-started from a previous fit."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from . import losses
from .body.base import BodyModel, BodyOutput, Params
from .camera import Camera
from .config import FitConfig, Stage
from .geometry import matrix_to_axis_angle, vertex_normals
from .keypoints import BODY, FACE, LEFT_HAND, RIGHT_HAND, SHOULDERS, TORSO_EDGES, Keypoints
from .scale_search import best_scale
from .scene import Scene

CAMERA_STAGE_KEYPOINTS = [2, 5, 9, 12]  # shoulders and hips


@dataclass
class Frame:
    """What the fitter reads for one image."""

    name: str
    keypoints: Keypoints
    depth_points: torch.Tensor | None = None  # (N, 3) camera-frame body points


@dataclass
class FitResult:
    name: str
    params: Params  # batch of one, detached
    vertices: torch.Tensor  # (V, 3) camera frame
    keypoints: torch.Tensor  # (118, 3) camera frame
    losses: dict[str, float]  # weighted value of each term at the end
    seconds: float
    stage_seconds: dict[str, float] = field(default_factory=dict)


class Fitter:
    """Fits one body model to frames seen by one camera, optionally inside a scene."""

    def __init__(self, body: BodyModel, camera: Camera, config: FitConfig,
                 scene: Scene | None = None,
                 on_stage: Callable[[str], None] | None = None) -> None:
        needs_scene = config.uses("penetration") or config.uses("contact")
        if needs_scene and scene is None:
            raise ValueError(f"configuration '{config.name}' needs a scene")
        self.body, self.camera, self.config, self.scene = body, camera, config, scene
        self.on_stage = on_stage  # told each stage's name as it starts (progress, cancelling)
        self.contact_part_ids = [body.contact_parts[p] for p in config.contact_parts
                                 if p in body.contact_parts]
        self.contact_ids = (torch.cat(self.contact_part_ids) if self.contact_part_ids
                            else torch.zeros(0, dtype=torch.long))

    # ------------------------------------------------------------------ public API
    def fit(self, frames: list[Frame], warm_start: Params | None = None,
            previous_keypoints: torch.Tensor | None = None) -> list[FitResult]:
        """Fit a batch of frames: from scratch with every stage, or (sequence mode) from
        ``warm_start`` with the configuration's sequence stages and the temporal term."""
        start = time.perf_counter()
        target, conf = self._targets(frames)
        depth = [f.depth_points for f in frames]
        has_hands = any(f.keypoints.has_hands for f in frames)
        stage_seconds: dict[str, float] = {}
        if warm_start is None:
            self._announce("initialise")
            params = self._initialise(frames, target, conf)
            stage_seconds["camera"] = time.perf_counter() - start
            stages = self.config.stages
            frozen_shape = False
        else:
            params = {k: v.detach().clone().expand(len(frames), *v.shape[1:]).contiguous()
                      for k, v in warm_start.items()}
            stages = [self.config.stages[i] for i in self.config.sequence_stages]
            frozen_shape = True
        final: dict[str, torch.Tensor] = {}
        rescaled = warm_start is not None or not self.config.scale_search
        for stage in stages:
            self._announce(stage.name)
            t0 = time.perf_counter()
            if not rescaled and self._scene_stage(stage):
                self._rescale(params)
                rescaled = True
            free = ["transl", "global_orient", *self.body.pose_group()]
            if stage.optimize_shape and not frozen_shape:
                free += self.body.shape_group()
            if stage.optimize_hands and has_hands:
                free.append("hand_pose")
            final = self._run_stage(stage, params, free, target, conf, depth,
                                    previous_keypoints)
            stage_seconds[stage.name] = stage_seconds.get(stage.name, 0.0) + (
                time.perf_counter() - t0)
        with torch.no_grad():
            out = self.body(params)
        elapsed = (time.perf_counter() - start) / len(frames)
        return [FitResult(
            name=f.name, params={k: v[i:i + 1].detach().clone() for k, v in params.items()},
            vertices=out.vertices[i].detach(), keypoints=out.keypoints[i].detach(),
            losses={k: float(v[i]) for k, v in final.items()}, seconds=elapsed,
            stage_seconds={k: v / len(frames) for k, v in stage_seconds.items()})
            for i, f in enumerate(frames)]

    def _announce(self, stage: str) -> None:
        if self.on_stage is not None:
            self.on_stage(stage)

    # ------------------------------------------------------------------ objective
    def _targets(self, frames: list[Frame]) -> tuple[torch.Tensor, torch.Tensor]:
        data = torch.tensor(np.stack([f.keypoints.data for f in frames]), dtype=torch.float32)
        conf = data[..., 2] * self.body.keypoint_mask
        conf[:, self.config.ignore_keypoints] = 0
        return data[..., :2], conf

    def _terms(self, stage: Stage, out: BodyOutput, params: Params, target: torch.Tensor,
               conf: torch.Tensor, depth: list, previous: torch.Tensor | None
               ) -> dict[str, torch.Tensor]:
        """Weighted value (B,) of every active term of a stage."""
        w = stage.weights
        cfg, body = self.config, self.body
        joint_weight = torch.zeros_like(conf)
        joint_weight[:, BODY] = w.get("body", 0)
        joint_weight[:, LEFT_HAND] = w.get("hands", 0)
        joint_weight[:, RIGHT_HAND] = w.get("hands", 0)
        joint_weight[:, FACE] = w.get("face", 0)
        terms = {"data": losses.keypoint_data(out, self.camera, target,
                                              (joint_weight * conf) ** 2, cfg.data_rho),
                 "joint_limits": cfg.joint_limit_weight * body.joint_limits(params)}
        priors = {"pose_prior": body.pose_prior, "shape": body.shape_prior,
                  "bending": body.bending_prior, "hand_prior": body.hand_prior}
        for name, prior in priors.items():
            if w.get(name, 0) > 0:
                terms[name] = w[name] * prior(params)
        if w.get("self_penetration", 0) > 0:
            terms["self_penetration"] = w["self_penetration"] * losses.self_penetration(out, body)
        if w.get("penetration", 0) > 0:
            terms["penetration"] = w["penetration"] * losses.penetration(out, body, self.scene)
        if w.get("contact", 0) > 0 and len(self.contact_ids):
            terms["contact"] = w["contact"] * losses.contact(
                out, body, self.scene, self.contact_ids, cfg.contact_rho,
                cfg.contact_max_angle, cfg.contact_max_distance)
        if w.get("depth", 0) > 0 and any(d is not None for d in depth):
            terms["depth"] = w["depth"] * losses.depth_data(out, body, depth, cfg.depth_rho)
        if w.get("temporal", 0) > 0 and previous is not None:
            terms["temporal"] = w["temporal"] * losses.temporal(out, previous)
        return terms

    def _run_stage(self, stage: Stage, params: Params, free: list[str], target: torch.Tensor,
                   conf: torch.Tensor, depth: list, previous: torch.Tensor | None
                   ) -> dict[str, torch.Tensor]:
        for name, value in params.items():
            value.requires_grad_(name in free)
        variables = [params[n] for n in free]
        optimizer = torch.optim.LBFGS(variables, lr=1.0,
                                      max_iter=stage.max_iter or self.config.max_iter,
                                      line_search_fn="strong_wolfe", tolerance_grad=1e-7,
                                      tolerance_change=1e-10, history_size=20)
        last: dict[str, torch.Tensor] = {}

        def closure() -> torch.Tensor:
            optimizer.zero_grad()
            out = self.body(params)
            terms = self._terms(stage, out, params, target, conf, depth, previous)
            total = sum(t.sum() for t in terms.values())
            total.backward()
            last.clear()
            last.update({k: v.detach() for k, v in terms.items()})
            return total

        previous_loss = math.inf
        for _ in range(stage.max_calls or self.config.max_calls):
            backup = [v.detach().clone() for v in variables]
            loss = float(optimizer.step(closure).detach())
            if not math.isfinite(loss) or not all(bool(torch.isfinite(v).all())
                                                  for v in variables):
                with torch.no_grad():
                    for v, b in zip(variables, backup):
                        v.copy_(b)
                break
            if abs(previous_loss - loss) <= self.config.ftol * max(1.0, abs(loss)):
                break
            previous_loss = loss
        for value in params.values():
            value.requires_grad_(False)
        return last

    # ------------------------------------------------------------------ scene-aware depth
    @staticmethod
    def _scene_stage(stage: Stage) -> bool:
        return stage.weights.get("penetration", 0) > 0 or stage.weights.get("contact", 0) > 0

    def _rescale(self, params: Params) -> None:
        """Scale each body about the camera centre to where it best meets the scene (see
        :mod:`scale_search`), then refit shape and root to the scaled vertices, in place."""
        cfg, body = self.config, self.body
        with torch.no_grad():
            out = body(params)
            normals = vertex_normals(out.vertices, body.faces)
        scale = best_scale(out.vertices, normals, body.scene_vertices, self.contact_part_ids,
                           self.scene, cfg.uses("contact"), cfg.uses("penetration"),
                           cfg.contact_rho, cfg.contact_max_angle, cfg.contact_max_distance)
        if bool(((scale - 1).abs() < 0.01).all()):
            return
        goal = out.vertices * scale[:, None, None]
        with torch.no_grad():
            params["transl"] *= scale[:, None]
        self._minimise([params[n] for n in ["transl", "global_orient", *body.shape_group()]],
                       lambda: ((body(params).vertices - goal) ** 2).sum(-1).mean() * 1e4)

    def _minimise(self, variables: list[torch.Tensor],
                  objective: Callable[[], torch.Tensor]) -> None:
        """One L-BFGS call (strong Wolfe line search) on ``variables``, in place."""
        for v in variables:
            v.requires_grad_(True)
        optimizer = torch.optim.LBFGS(variables, lr=1.0, max_iter=self.config.max_iter,
                                      line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            optimizer.zero_grad()
            loss = objective()
            loss.backward()
            return loss

        optimizer.step(closure)
        for v in variables:
            v.requires_grad_(False)

    # ------------------------------------------------------------------ initialisation
    def _initialise(self, frames: list[Frame], target: torch.Tensor,
                    conf: torch.Tensor) -> Params:
        """Each of the body's starting postures, upright and facing the camera at the
        similar-triangles depth, refined by the camera stage; a copy turned by 180 degrees
        too when the shoulders are close in 2D (SMPLify-X). Per frame, the candidate whose
        body keypoints reproject best is kept."""
        body = self.body
        up = self.scene.up_in_camera() if self.scene is not None else torch.tensor(
            [0.0, -1.0, 0.0])
        width = (target[:, SHOULDERS[0]] - target[:, SHOULDERS[1]]).norm(dim=-1)
        turned = bool((width < self.config.flip_shoulder_px).any()) or bool(
            (conf[:, SHOULDERS[0]] * conf[:, SHOULDERS[1]] == 0).any())
        body_weight = torch.zeros_like(conf)
        body_weight[:, BODY] = conf[:, BODY] ** 2
        candidates, scores = [], []
        for posture in body.postures:
            params = body.init_params(len(frames), posture)
            with torch.no_grad():
                rest = body(params)
            depth = self._torso_depth(rest.keypoints, target, conf)
            for facing in (True, False) if turned else (True,):
                candidate = self._place(params, rest, target, conf, depth, up, facing)
                self._camera_stage(candidate, target, conf, depth)
                with torch.no_grad():
                    scores.append(losses.keypoint_data(body(candidate), self.camera, target,
                                                       body_weight, self.config.data_rho))
                candidates.append(candidate)
        best = torch.stack(scores).argmin(0)  # (B,)
        return {k: torch.stack([candidates[int(best[b])][k][b] for b in range(len(frames))])
                for k in candidates[0]}

    def _torso_depth(self, model_kp: torch.Tensor, target: torch.Tensor,
                     conf: torch.Tensor) -> torch.Tensor:
        """fx * mean 3D torso edge / mean 2D torso edge, per frame."""
        depths = []
        for b in range(target.shape[0]):
            e3, e2 = [], []
            for i, j in TORSO_EDGES + [SHOULDERS]:
                if conf[b, i] > 0 and conf[b, j] > 0:
                    e3.append((model_kp[0, i] - model_kp[0, j]).norm())
                    e2.append((target[b, i] - target[b, j]).norm())
            if not e2 or float(sum(e2)) < 1e-3:
                depths.append(torch.tensor(3.0))
            else:
                depths.append(self.camera.fx * torch.stack(e3).mean() / torch.stack(e2).mean())
        return torch.stack(depths).clamp(0.3, 30.0)

    def _place(self, params: Params, rest: BodyOutput, target: torch.Tensor,
               conf: torch.Tensor, depth: torch.Tensor, up: torch.Tensor,
               facing: bool) -> Params:
        body = self.body
        view = torch.tensor([0.0, 0.0, 1.0])
        horizontal = view - (view @ up) * up
        if horizontal.norm() < 1e-3:  # camera looking straight down or up
            horizontal = torch.tensor([0.0, 1.0, 0.0]) - up[1] * up
        horizontal = horizontal / horizontal.norm()
        forward = -horizontal if facing else horizontal
        # Rotation taking the model's (forward, up) to the camera's (forward, up).
        model_f, model_u = body.forward_axis(), body.up_axis()
        src = torch.stack([model_f, model_u, torch.linalg.cross(model_f, model_u)], 1)
        dst = torch.stack([forward, up, torch.linalg.cross(forward, up)], 1)
        rotation = dst @ src.T
        new = {k: v.clone() for k, v in params.items()}
        new["global_orient"][:] = matrix_to_axis_angle(rotation)
        torso = CAMERA_STAGE_KEYPOINTS
        offset = rotation @ rest.keypoints[0, torso].mean(0)
        for b in range(target.shape[0]):
            w = conf[b, torso]
            centre = (target[b, torso] * w[:, None]).sum(0) / w.sum() if w.sum() > 0 else \
                target[b, BODY][conf[b, BODY] > 0].mean(0)
            point = self.camera.backproject(centre[0], centre[1], depth[b])
            new["transl"][b] = point - offset
        return new

    def _camera_stage(self, params: Params, target: torch.Tensor, conf: torch.Tensor,
                      depth: torch.Tensor) -> None:
        """Optimise root rotation and translation on the torso keypoints, in place."""
        weight = torch.zeros_like(conf)
        weight[:, CAMERA_STAGE_KEYPOINTS] = conf[:, CAMERA_STAGE_KEYPOINTS] ** 2

        def objective() -> torch.Tensor:
            loss = losses.keypoint_data(self.body(params), self.camera, target, weight,
                                        self.config.data_rho)
            depth_error = (params["transl"][:, 2] - depth) ** 2
            return (loss + self.config.init_depth_weight * depth_error).sum()

        self._minimise([params["transl"], params["global_orient"]], objective)
