"""The annealed PROX optimisation: start search (initialisation.py), weighted stages (L-BFGS
with strong Wolfe line search), for a batch of frames or warm-started from a previous fit."""
from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from . import keypoint_terms, lbfgs, losses
from .body.base import BodyModel, BodyOutput, Params, VertexSubset
from .body.by_frame import FRAME, by_frame, one_frame
from .camera import Camera
from .config import FitConfig, Stage
from .geometry import VertexNormals, picked, ray_points_at, sum_into, turned_onto_ray
from .keypoints import (ANKLES, ARMS, BODY, FACE, FEET, FOREARMS, HIDDEN, HIPS, KNEES, MID_HIP,
                        LABELLINGS, LEFT_HAND, RIGHT_HAND, SEEN, SHINS, SHOULDERS, Keypoints,
                        ankle_seen, cut_legs, nothing_below_knees, side_swap, thighs_hanging,
                        thighs_hidden, toes_unseen)
from .initialisation import best_start
from .keypoint_objective import KeypointObjective, goal_distance
from .rescale import rescaled
from .scale_search import (STANDING_PARTS, best_scale, carrying_vertices, feet_carried,
                           kneelers_toes, lying, normal_vertices, size_prior, standing_counts,
                           standing_legs, toe_vertices, unseen_feet_on_kneeling_legs)
from .scene import Scene
from .with_gradient import with_gradient


# Leg restarts (FitConfig.leg_restarts): the least the ankle must move for a restart to
# be tried (m); the keypoint-only L-BFGS iterations that pose it; and how far (m) from
# their goal its keypoints may end (farther, a straight leg would have to bend forward).
MIRROR_MIN = 0.1
MIRROR_ITERATIONS = 20
MIRROR_REACH = 0.05
# Knee restarts (FitConfig.knee_restarts): a leg whose knee the fit misses by more than
# this (px) is also restarted posed onto its knee's and ankle's camera rays.
KNEE_MISS = 50.0
KNEE_SLACK = 1.2  # a ray may pass this many limb lengths away (geometry.ray_points_at)
# ... and that pose, made of detected keypoints (a few centimetres off the joints) with
# the foot carried along, may be missed by this much (m): the stage after the restart
# fits it (seed 49's kneeler, its pose missed by 14 cm: 253 -> 67 mm).
KNEE_REACH = 0.2

# What the scene stages may add to a frame's data term (robust px^2) besides multiplying
# it by FitConfig.scene_data_guard: bending a standing body seen exactly out of a floor
# scanned 2 cm high costs about 900 (its joints end 4-6 cm off). Of 648 benchmark frames
# (twelve seeds), 23 tripled their data term in the scene stages (undone, 20 gained PJE,
# and sitters sat 4-13 % of their vertices deep in their seats) and 6 also added more
# than this (a seated body thrown from a seat it had sunk 7 cm into: 334 -> 4163).
SCENE_GUARD_FLOOR = 1000.0

# A foot whose toes the detector did not clearly see, and which the placed fit sinks more
# than this (m) into the scene with its toes, is turned toward its neutral ankle before
# the scene stages (FitConfig.lift_sunk_feet): keeping the first of these shares of its
# turn that brings its toes within SUNK_TOES, or else the one that sinks them least,
# where that lifts them by LIFT_MIN (m) or more (less, the scene stages bend it as far).
SUNK_TOES = 0.02
LIFT_KEPT = (2 / 3, 1 / 3, 0.0)
LIFT_MIN = 0.01

# Terms that read the posed mesh; stages without them pose keypoints and spheres only,
# and stages with the scene terms alone pose only the vertices those read.
SCENE_TERMS = ("penetration", "contact")
MESH_TERMS = (*SCENE_TERMS, "depth")
# Terms that read more of the body than its keypoints and pose (the mesh, the collision
# spheres): a stage with any goes through autograd. The temporal term reads only the
# keypoints (and the previous frame's fit).
GRAPH_TERMS = (*MESH_TERMS, "self_penetration")
# Priors that measure how far a posture is from the model's rest pose, which the start
# choice may leave out (FitConfig.start_choice_priors).
POSTURE_PRIORS = ("pose_prior", "bending")
# Terms that shape a fit but never rank candidates (FitConfig.level_weight).
UNRANKED = ("level",)


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
    stage_evaluations: dict[str, float] = field(default_factory=dict)  # body rows per frame
    events: list[str] = field(default_factory=list)  # numerical trouble met on the way
    swapped: list[str] = field(default_factory=list)  # parts whose sides were relabelled
    underside_gap: float | None = None  # m (quality.underside_gap), where already measured
    # Which of the frame's distinct starts (best first) its fit went on from; None where
    # it had one.
    start: int | None = None


@dataclass
class _Choice:
    """When each frame keeps one of its candidate rows (after the stage numbered
    ``after``, counting from 1) and by what (:meth:`Fitter._choose`): the objective,
    with the posture priors if ``priors``, the arms' keypoints if ``arms`` and the feet's
    but in the frames ``feet_left_out`` ((frames,) bool; None: none), plus the scene's
    cost if ``by_scene``, each frame's contact parts ``uncounted`` ((frames, P) bool;
    None: none) counted as missing there."""

    after: int
    by_scene: bool = True
    priors: bool = True
    arms: bool = True
    feet_left_out: torch.Tensor | None = None
    uncounted: torch.Tensor | None = None


@dataclass
class _Held:
    """What stays put while a stage runs (:meth:`Fitter._held`): the keypoints' weights
    (B, K), the upright term's per frame (B,; 0 where no ankle is seen), the legs cut off
    ((B, 2) float; None: none), the weighted priors (name -> weight, prior, parameters it
    reads) and the values of those of them that read no free parameter (the shape of a
    warm-started frame)."""

    weights: torch.Tensor
    upright: torch.Tensor
    cut: torch.Tensor | None
    priors: dict[str, tuple[float, Callable[[Params], torch.Tensor], list[str]]]
    fixed: dict[str, torch.Tensor]


@dataclass
class _Rows:
    """What the stages fit, one row per frame and candidate: the parameters, the keypoints
    as labelled for that row (and the detector's confidences of the body joints), depth
    points and the parts relabelled."""

    params: Params
    target: torch.Tensor  # (rows, K, 2)
    conf: torch.Tensor  # (rows, K)
    detected: torch.Tensor  # (rows, 25), neck and hips included
    depth: list
    labels: list[tuple[str, ...]]

    def widened(self, variants: list[Params]) -> "_Rows":
        """Each row followed by the same row with each variant's parameters."""
        count = 1 + len(variants)
        params = {k: torch.stack([p[k] for p in [self.params, *variants]], 1)
                  .flatten(0, 1).contiguous() for k in self.params}
        return _Rows(params, self.target.repeat_interleave(count, 0),
                     self.conf.repeat_interleave(count, 0),
                     self.detected.repeat_interleave(count, 0),
                     [d for d in self.depth for _ in range(count)],
                     [lab for lab in self.labels for _ in range(count)])

    def taken(self, rows: list[int]) -> "_Rows":
        return _Rows({k: v[rows].contiguous() for k, v in self.params.items()},
                     self.target[rows], self.conf[rows], self.detected[rows],
                     [self.depth[r] for r in rows],
                     [self.labels[r] for r in rows])


class Fitter:
    """Fits one body model to frames seen by one camera, optionally inside a scene."""

    def __init__(self, body: BodyModel, camera: Camera, config: FitConfig,
                 scene: Scene | None = None,
                 on_stage: Callable[[str], None] | None = None) -> None:
        needs_scene = config.uses("penetration") or config.uses("contact")
        if needs_scene and scene is None:
            raise ValueError(f"configuration '{config.name}' needs a scene")
        self.body, self.camera, self.config, self.scene = body, camera, config, scene
        # World up in camera coordinates (without a scene, the camera's -y).
        self.up = scene.up_in_camera() if scene is not None else torch.tensor([0.0, -1.0, 0.0])
        self.on_stage = on_stage  # told each stage's name as it starts (progress, cancelling)
        self.contact_part_ids = [body.contact_parts[p] for p in config.contact_parts
                                 if p in body.contact_parts]
        # (P,) bool over those parts: a standing body's, those a hidden legs' ranking
        # counts as missing, and those a hanging-thighs frame's start choice does
        self.standing_parts = self._contact_mask(STANDING_PARTS)
        self.hidden_leg_parts = self._contact_mask(config.hidden_leg_uncounted)
        self.hanging_thigh_parts = self._contact_mask(config.hanging_thighs_uncounted)
        self.carrying = carrying_vertices(body.contact_parts, body.num_vertices)
        # How deep each vertex of the scene terms rests inside a surface it touches
        # (config.soft_sink; None: on it) and may enter it unpenalised (one depth for all
        # without a sink)
        self.contact_sink: torch.Tensor | None = None
        self.penetration_tolerance: float | torch.Tensor = config.penetration_tolerance
        self.toes, self.scene_subset, self.penetration_vertices, self.contact_normals = (
            None, None, None, None)
        # The toes' vertices, posed alone (lift_sunk_feet), and which foot each is of:
        # (2, toes) right, then left
        self.toe_subset: VertexSubset | None = None
        self.toe_sides: torch.Tensor | None = None
        # The normals the scale search reads (scale_search.normal_vertices; a kernel: 1.2 ms
        # for two whole bodies where geometry.vertex_normals took 3.1); a fit without a
        # scene never reads them
        self.vertex_normals: VertexNormals | None = None
        if needs_scene:
            self.vertex_normals = VertexNormals(
                body.faces, normal_vertices(body.scene_vertices, self.contact_part_ids))
            with torch.no_grad():  # the standing mean body, which both sets are chosen on
                rest = body(body.init_params(1))
            sides = toe_vertices(body.vertex_parts, rest.vertices[0],
                                 rest.keypoints[0, ANKLES])
            if config.scale_free_toes:  # the vertices the scale search does not count
                self.toes = sides.any(0)
            self.toe_subset = body.vertex_subset(torch.nonzero(sides.any(0)).flatten())
            self.toe_sides = sides[:, self.toe_subset.ids]
            self.scene_subset, self.penetration_vertices, self.contact_normals = (
                self._scene_vertices(rest.vertices[0]))
            # How deep each vertex may enter the scan beyond penetration_tolerance: the
            # resting flesh's sink, the feet's tolerance (disjoint parts)
            sink = config.soft_sink * losses.part_vertices(
                body.contact_parts, losses.SOFT_PARTS, body.num_vertices)
            give = sink if config.foot_tolerance <= 0 else sink + config.foot_tolerance * (
                torch.tensor([p in losses.FEET_PARTS for p in body.vertex_parts]))
            if self.penetration_vertices is not None and bool(give.any()):
                self.penetration_tolerance = config.penetration_tolerance + give[
                    self.scene_subset.ids[self.penetration_vertices[0]]]
            if config.soft_sink > 0 and self.contact_normals is not None:
                self.contact_sink = sink[self.scene_subset.ids[self.contact_normals.ids]]
        self.events: list[str] = []  # of the current fit (see FitResult.events)
        self._size_unit: torch.Tensor | None = None  # of the current fit (see _sizes)
        # The frames last initialised: their keypoints, which were labelled as detected,
        # starts, labellings and events.
        self._started: tuple[list[np.ndarray], list[bool], Params, list[tuple[str, ...]],
                             list[str]] = ([], [], {}, [], [])
        self.evaluations = 0  # body rows evaluated in the current fit

    def _scene_vertices(self, rest: torch.Tensor) -> tuple[
            VertexSubset | None, tuple[torch.Tensor, torch.Tensor] | None,
            VertexNormals | None]:
        """The vertices the scene terms read (the penetration term's, chosen on the
        standing mean body ``rest`` (V, 3), the contact vertices and the corners of the
        faces around them, whose normals they need), and those terms' vertex indices and
        contact normals within that subset."""
        body = self.body
        penetration = (losses.penetration_vertices(body, self.config.penetration_spacing,
                                                   rest)
                       if self.config.uses("penetration") else None)
        contact = torch.cat(self.contact_part_ids) if self.contact_part_ids else None
        ids = [] if penetration is None else [penetration[0]]
        if contact is not None:
            ids.append(body.faces[torch.isin(body.faces, contact).any(1)].flatten())
        if not ids:  # contact asked for, but the model has no contact vertices
            return None, None, None
        subset = body.vertex_subset(torch.cat(ids))
        local = torch.full((body.num_vertices,), -1, dtype=torch.long)
        local[subset.ids] = torch.arange(len(subset.ids))
        faces = local[body.faces]
        normals = (None if contact is None
                   else VertexNormals(faces[(faces >= 0).all(1)], local[contact]))
        return (subset, None if penetration is None else (local[penetration[0]], penetration[1]),
                normals)

    def _hanging_uncounted(self, target: torch.Tensor, conf: torch.Tensor
                           ) -> torch.Tensor | None:
        """(B, P) bool: per frame (keypoints ``target`` (B, K, 2), the detector's
        confidences ``conf`` (B, K)), the contact parts its start choice counts as missing
        (``config.hanging_thighs_uncounted``, where no ankle is seen and the thighs are
        seen hanging along world down); None where none is."""
        if not bool(self.hanging_thigh_parts.any()):
            return None
        down = self.camera.image_direction(target[:, MID_HIP], -self.up)
        hanging = ~ankle_seen(conf) & thighs_hanging(target, conf, down)
        return hanging[:, None] & self.hanging_thigh_parts if bool(hanging.any()) else None

    def _contact_mask(self, names: Sequence[str]) -> torch.Tensor:
        """(P,) bool over the contact parts the fit uses: which are among ``names``."""
        return torch.tensor([p in names for p in self.config.contact_parts
                             if p in self.body.contact_parts], dtype=torch.bool)

    # ------------------------------------------------------------------ public API
    def fit(self, frames: list[Frame], warm_start: Params | None = None,
            previous_keypoints: torch.Tensor | None = None,
            start: int | Sequence[int | None] | None = None, sized_as: Params | None = None,
            as_detected: Sequence[bool] | None = None) -> list[FitResult]:
        """Fit a batch of frames: from scratch with every stage (given ``start``, one for
        all frames or one per frame, from that of each frame's distinct starts alone, best
        first; None: the better after the start stages; in the frames ``as_detected``, the
        keypoints labelled as the detector has them, whatever ``config.swap_sides``), or
        (sequence mode) from ``warm_start`` with the configuration's sequence stages and
        the temporal term, the scale search's size prior centred on the size of the body
        ``sized_as`` (one row; without it, on the prior-mean body's: see
        :meth:`_sizes`)."""
        self._size_unit = None if sized_as is None else self.body.relative_size(sized_as)
        starts = list(start) if isinstance(start, Sequence) else [start] * len(frames)
        fixed = [False] * len(frames) if as_detected is None else list(as_detected)
        if len(starts) != len(frames) or len(fixed) != len(frames):
            raise ValueError(f"{len(frames)} frames, {len(starts)} starts and {len(fixed)} "
                             "labellings given: one of each per frame")
        with self._counting():
            return self._fit(frames, warm_start, previous_keypoints, starts, fixed)

    def start_labelling(self, frame: Frame) -> tuple[str, ...]:
        """The parts whose left and right the best start of ``frame`` exchanges: the start
        search alone (:attr:`evaluations` counts its body rows)."""
        self.evaluations = 0
        with self._counting():
            return self.initialise([frame])[1][0]

    @contextmanager
    def _counting(self) -> Iterator[None]:
        hook = self.body.register_forward_pre_hook(self._count)
        try:
            yield
        finally:
            hook.remove()

    def _count(self, _module: torch.nn.Module, inputs: tuple) -> None:
        """Forward pre-hook: body rows evaluated (a batch of B bodies counts B)."""
        self._counted(len(inputs[0]["transl"]))

    def _counted(self, rows: int) -> None:
        """Body rows evaluated, by the forward's hook or by a keypoint path's objective."""
        self.evaluations += rows

    def _fit(self, frames: list[Frame], warm_start: Params | None,
             previous_keypoints: torch.Tensor | None, start: list[int | None],
             as_detected: list[bool]) -> list[FitResult]:
        began = time.perf_counter()
        self.events = []
        self.evaluations = 0
        stage_evaluations: dict[str, int] = {}
        target, conf = self._targets(frames)
        detected = conf[:, BODY].clone()  # neck and hips included
        cfg = self.config
        feet_left_out = (thighs_hidden(conf) if warm_start is None and cfg.start_other_thighs
                         and cfg.start_thighs_hidden and not cfg.start_choice_feet else None)
        uncounted = self._hanging_uncounted(target, conf) if warm_start is None else None
        conf[:, self.config.ignore_keypoints] = 0
        has_hands = any(f.keypoints.has_hands for f in frames)
        stage_seconds: dict[str, float] = {}
        if warm_start is None:
            self._announce("initialise")
            params, labels = self.initialise(frames, as_detected)
            stage_seconds["initialise"] = time.perf_counter() - began
            stage_evaluations["initialise"] = self.evaluations
            stages = self.config.stages
            frozen_shape = False
        else:
            params = {k: v.detach().clone().expand(len(frames), *v.shape[1:]).contiguous()
                      for k, v in warm_start.items()}
            labels = self._closest_labelling(target, conf, previous_keypoints)
            stages = [self.config.stages[i] for i in self.config.sequence_stages]
            frozen_shape = True
        # each row's frame: what mixes rows is worked out frame by frame (body.by_frame)
        params[FRAME] = torch.arange(len(frames)).repeat_interleave(
            len(params["transl"]) // len(frames))
        # Rows per frame fitted side by side (starts, then arm restarts, then leg
        # restarts), and when and how each frame keeps its best row: the scene's cost
        # takes part for starts and legs, the posture priors for restarts (for starts as
        # configured).
        keep = len(labels) // len(frames)
        starts: list[int | None] = [None] * len(frames)
        counts = [keep] * len(frames)  # rows per frame, from here on
        if keep > 1:
            distinct = [not all(torch.equal(v[b * keep], v[b * keep + 1])
                                for v in params.values()) for b in range(len(frames))]
            starts = [(0 if s is None else s) if d else None for d, s in zip(distinct, start)]
            if any(s is not None for s in start):
                counts = [keep if s is None else 1 for s in start]
                taken = [b * keep + r for b, s in enumerate(start)
                         for r in (range(keep) if s is None else [s])]
                params = {k: v[taken] for k, v in params.items()}
                labels = [labels[r] for r in taken]
        choice = _Choice(self.config.start_stages, priors=self.config.start_choice_priors,
                         arms=self.config.start_choice_arms, feet_left_out=feet_left_out,
                         uncounted=uncounted)
        rows_of = torch.tensor(counts)
        rows = _Rows(params, target.repeat_interleave(rows_of, 0),
                     conf.repeat_interleave(rows_of, 0), detected.repeat_interleave(rows_of, 0),
                     [f.depth_points for f, n in zip(frames, counts) for _ in range(n)], labels)
        for b, label in enumerate(labels):  # fit the keypoints as relabelled
            order = side_swap(label)
            rows.target[b], rows.conf[b] = rows.target[b, order], rows.conf[b, order]
            rows.detected[b] = rows.detected[b, order[BODY]]
        final: dict[str, torch.Tensor] = {}
        rescaled = not self.config.scale_search or (
            warm_start is not None and not self.config.sequence_scale_search)
        placed = warm_start is not None  # at the depth cloud's distance
        before_scene: tuple[Params, dict[str, torch.Tensor]] | None = None
        for index, stage in enumerate(stages):
            self._announce(stage.name)
            if not placed and stage.weights.get("depth", 0) > 0:
                t0, before = time.perf_counter(), self.evaluations
                self._rescale(rows.params, self._depth_scale(rows.params, rows.depth),
                              len(frames))
                stage_seconds["depth_placement"] = time.perf_counter() - t0
                stage_evaluations["depth_placement"] = self.evaluations - before
                placed = True
            if not rescaled and self._scene_stage(stage):
                t0, before = time.perf_counter(), self.evaluations
                if cfg.point_unseen_feet:
                    rows.params.update(self._pointed_feet(rows.params,
                                                          rows.detected > SEEN))
                if cfg.hidden_leg_postures and warm_start is None and max(counts) == 1:
                    rows = self._hidden_leg_postures(rows, stages[index - 1])
                scale, _ = self._scale_search(rows.params, rows.detected)
                self._rescale(rows.params, scale, len(frames))
                if cfg.lift_sunk_feet and warm_start is None:
                    rows.params.update(self._lifted_feet(rows.params, rows.detected > SEEN))
                stage_seconds["scale_search"] = time.perf_counter() - t0
                stage_evaluations["scale_search"] = self.evaluations - before
                rescaled = True
            if (before_scene is None and warm_start is None and final and max(counts) == 1
                    and self.config.scene_data_guard > 0 and self._scene_stage(stage)):
                before_scene = ({k: v.detach().clone() for k, v in rows.params.items()}, final)
            t0, before = time.perf_counter(), self.evaluations
            moves = self.config.scene_stages_translate or not self._scene_stage(stage)
            free = [*(["transl"] if moves else []), "global_orient", *self.body.pose_group()]
            if stage.optimize_shape and not frozen_shape:
                free += self.body.shape_group()
            if stage.optimize_hands and has_hands:
                free.append("hand_pose")
            final = self._run_stage(stage, rows.params, free, rows.target, rows.conf,
                                    rows.depth, previous_keypoints, lbfgs.sized_groups(counts))
            if max(counts) > 1 and index + 1 == choice.after:
                best = self._choose(choice, stage, rows, final, counts)
                if index + 1 == self.config.start_stages and warm_start is None:
                    starts = [r - group.start if s is not None and n > 1 else s
                              for s, r, group, n in zip(starts, best, lbfgs.sized_groups(counts),
                                                        counts)]
                rows, final = rows.taken(best), {k: v[best] for k, v in final.items()}
                counts = [1] * len(frames)
            if (warm_start is None and self.config.arm_restarts
                    and index + 1 == self.config.start_stages < len(stages)):
                variants = self.body.arm_restarts(rows.params)
                if variants:
                    rows = rows.widened(variants)
                    counts = [1 + len(variants)] * len(frames)
                    choice = _Choice(index + 2, by_scene=False)
            if (warm_start is None and max(counts) == 1
                  and (self.config.leg_restarts or self.config.forearm_restarts
                       or self.config.shoulder_restarts)
                  and index == self.config.start_stages and index + 1 < len(stages)
                  and self._scales_searched()):
                restarts = self._limb_restarts(rows)
                if restarts:  # each frame's own: a turn another frame needed is not fitted
                    tried = torch.stack([torch.ones(len(rows.labels), dtype=torch.bool),
                                         *(t for _, t in restarts)], 1)
                    rows = rows.widened([v for v, _ in restarts]).taken(
                        tried.flatten().nonzero().flatten().tolist())
                    counts, choice = tried.sum(1).tolist(), _Choice(index + 2)
            stage_seconds[stage.name] = stage_seconds.get(stage.name, 0.0) + (
                time.perf_counter() - t0)
            stage_evaluations[stage.name] = (stage_evaluations.get(stage.name, 0)
                                             + self.evaluations - before)
        if before_scene is not None:
            final = self._undo_broken_scene(frames, stages[-1], rows, final, *before_scene)
        params, labels = rows.params, rows.labels
        before = self.evaluations
        with torch.no_grad():
            out = self.body(params)
        stage_evaluations["output"] = self.evaluations - before
        elapsed = (time.perf_counter() - began) / len(frames)
        return [FitResult(
            name=f.name, params={k: v[i:i + 1].detach().clone() for k, v in params.items()
                                 if k != FRAME},
            vertices=out.vertices[i].detach(), keypoints=out.keypoints[i].detach(),
            losses={k: float(v[i]) for k, v in final.items()}, seconds=elapsed,
            stage_seconds={k: v / len(frames) for k, v in stage_seconds.items()},
            stage_evaluations={k: v / len(frames) for k, v in stage_evaluations.items()},
            events=list(self.events), swapped=list(labels[i]), start=starts[i])
            for i, f in enumerate(frames)]

    def _undo_broken_scene(self, frames: list[Frame], stage: Stage, rows: _Rows,
                           terms: dict[str, torch.Tensor], kept: Params,
                           kept_terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Give back, in place, the body from before the scene stages (``kept``, whose
        terms were ``kept_terms``) to each frame whose scene stages multiplied its data
        term by more than ``config.scene_data_guard`` and added SCENE_GUARD_FLOOR, with
        an event naming it; returns the last ``stage``'s terms (``terms`` for the other
        frames). Only frames fitted from scratch are guarded: no previous keypoints."""
        broke = (terms["data"] > self.config.scene_data_guard * kept_terms["data"]
                 + SCENE_GUARD_FLOOR).nonzero().flatten().tolist()
        if not broke:
            return terms
        for b in broke:
            self.events.append(
                f"{frames[b].name}: scene stages undone, they took the data term from "
                f"{float(kept_terms['data'][b]):.0f} to {float(terms['data'][b]):.0f}")
        undone = rows.taken(broke)
        undone.params = {k: v[broke] for k, v in kept.items()}
        with torch.no_grad():
            redone = self._terms(stage, undone.params, undone.target, undone.conf,
                                 undone.depth, None)(
                self.body(undone.params, vertices=self._mesh_read(stage)))
        index = torch.tensor(broke)
        for name, value in undone.params.items():
            rows.params[name] = rows.params[name].index_copy(0, index, value)
        return {k: v.index_copy(0, index, redone[k]) for k, v in terms.items()}

    def _choose(self, choice: _Choice, stage: Stage, rows: _Rows,
                terms: dict[str, torch.Tensor], counts: list[int]) -> list[int]:
        """The row each frame keeps (``counts`` candidates per frame, fitted by ``stage``
        to ``terms``) as ``choice`` says; without the arms or feet, only the data term
        changes."""
        if not choice.arms or choice.feet_left_out is not None:
            conf = rows.conf.clone()
            if not choice.arms:
                conf[:, ARMS] = 0
            if choice.feet_left_out is not None:
                left_out = choice.feet_left_out.repeat_interleave(
                    torch.tensor(counts)).nonzero().flatten()
                conf[left_out[:, None], FEET] = 0
            with torch.no_grad():
                out = self.body(rows.params, vertices=False)
                terms = {**terms, "data": self._data_term(stage, out, rows.target, conf)}
        uncounted = (None if choice.uncounted is None else
                     choice.uncounted.repeat_interleave(torch.tensor(counts), 0))
        return self._best_rows(rows.params, rows.detected, terms, counts, choice.by_scene,
                               choice.priors, uncounted)

    def _best_rows(self, params: Params, detected: torch.Tensor,
                   terms: dict[str, torch.Tensor],
                   counts: list[int], by_scene: bool, priors: bool = True,
                   uncounted: torch.Tensor | None = None) -> list[int]:
        """Rows (one per frame) of the candidates, ``counts`` per frame (each frame's rows
        consecutive), with the lowest objective (``terms``; without the
        POSTURE_PRIORS unless ``priors``) plus, ``by_scene`` with a scale search,
        ``start_scene_weight`` times how badly each can meet the scene at its best scale
        (the body joints ``detected`` (rows, 25) as :meth:`_scale_search` reads them)
        and, with ``start_choice_size``, the size prior at that scale; the contact parts
        ``uncounted`` ((P,) bool, or (rows, P)) count as missing."""
        score = sum(v for k, v in terms.items()
                    if (priors or k not in POSTURE_PRIORS) and k not in UNRANKED)
        if by_scene and self.config.start_scene_weight > 0 and self._scales_searched():
            score = score + self.config.start_scene_weight * self._scene_costs(
                params, detected, score, counts, uncounted)
        return [group.start + int(score[group].argmin())
                for group in lbfgs.sized_groups(counts)]

    def _scene_costs(self, params: Params, detected: torch.Tensor, score: torch.Tensor,
                     counts: list[int], uncounted: torch.Tensor | None = None
                     ) -> torch.Tensor:
        """Per candidate row (``counts`` per frame), how badly it can meet the scene at
        its best scale: :meth:`_scale_search`'s cost, plus, with ``start_choice_size``,
        the size prior there. That sum is what the search minimises, so each frame's rows
        are then searched in the order of their ``score`` (the objective), each skipping
        the scales at which it cannot beat its frame's best so far: the same choice, for
        a fifth fewer scales evaluated on the speed benchmark."""
        search, sizes = self._scale_searcher(params, detected, uncounted=uncounted)
        if not self.config.start_choice_size:
            return search(torch.arange(len(score)))[1]
        weight = self.config.start_scene_weight
        frame = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
        ranked = [group.start + score[group].argsort(stable=True)
                  for group in lbfgs.sized_groups(counts)]
        best = torch.full((len(counts),), math.inf)  # each frame's least total so far
        costs = torch.empty_like(score)
        for rank in range(max(counts)):
            rows = torch.stack([order[rank] for order in ranked if rank < len(order)])
            scale, cost = search(rows, (best[frame[rows]] - score[rows]) / weight)
            costs[rows] = cost + size_prior(scale, self._size_weight(), sizes[rows])
            best.scatter_reduce_(0, frame[rows], score[rows] + weight * costs[rows], "amin")
        return costs

    def _limb_restarts(self, rows: _Rows) -> list[tuple[Params, torch.Tensor]]:
        """Copies of ``rows.params`` with a limb turned until its end lies on the other
        point of its camera ray at the same distance from the pivot, the rest of the body
        held: with ``leg_restarts``, per leg, the shin and foot about the knee (a shin
        seen from in front projects alike tucked back with the foot in the air, or down to
        the floor) and, with ``hip_restarts`` where the knee is not clearly seen, the
        whole leg about the hip, then both legs so (a seated person's thighs hidden under a
        table point toward the camera or hang down alike); with ``knee_restarts``, per
        leg, the leg posed onto its knee's and ankle's camera rays
        (:meth:`_legs_onto_rays`); with ``forearm_restarts``, per arm, the forearm about
        the elbow (it projects alike pointing toward the camera or away); with
        ``shoulder_restarts``, per arm, the whole arm about the shoulder (an arm reaching
        toward the camera projects alike reaching back). With each, which rows are
        restarts worth trying ((rows,) bool): those whose ankle the detector clearly saw
        (for the rays, whose knee the fit misses; for a forearm, whose wrist it reported
        at least HIDDEN; for an arm, whose elbow), whose first point moved moves by at
        least MIRROR_MIN and could be posed there within MIRROR_REACH (a straight leg would
        bend forward; KNEE_REACH on the rays); none for a turn without such a row."""
        body = self.body
        with torch.no_grad():
            kp = body(rows.params, vertices=False).keypoints[:, BODY]
        goals, useful, reach = [], [], []

        def add(chain: list[int], moved: torch.Tensor, worth: torch.Tensor,
                within: float = MIRROR_REACH) -> None:
            useful.append(worth & ((moved[:, 0] - kp[:, chain[0]]).norm(dim=-1) >= MIRROR_MIN))
            reach.append(within)
            goal = kp.clone()
            goal[:, chain] = torch.where(useful[-1][:, None, None], moved, kp[:, chain])
            goals.append(goal)

        def add_turn(pivot: int, chain: list[int], worth: torch.Tensor) -> None:
            add(chain, turned_onto_ray(kp[:, pivot], kp[:, chain]), worth)

        both, both_useful = kp.clone(), torch.ones(len(kp), dtype=torch.bool)
        legs = zip(HIPS, SHINS) if self.config.leg_restarts else ()
        for hip, (knee, foot) in legs:
            seen = rows.conf[:, foot[0]] > SEEN
            add_turn(knee, foot, seen)
            if self.config.hip_restarts:
                leg = [foot[0], knee, *foot[1:]]
                add_turn(hip, leg, seen & (rows.conf[:, knee] <= SEEN))
                both[:, leg] = goals[-1][:, leg]
                both_useful &= useful[-1]
            if self.config.knee_restarts:
                for moved, worth in self._legs_onto_rays(kp, rows, hip, knee, foot):
                    add([knee, *foot], moved, worth, KNEE_REACH)
        if self.config.forearm_restarts:
            for elbow, wrist in FOREARMS:
                add_turn(elbow, [wrist], rows.detected[:, wrist] >= HIDDEN)
        if self.config.shoulder_restarts:
            for shoulder, (elbow, wrist) in zip(SHOULDERS, FOREARMS):
                add_turn(shoulder, [elbow, wrist], rows.detected[:, elbow] >= HIDDEN)
        if self.config.leg_restarts and self.config.hip_restarts:
            goals.append(both)
            useful.append(both_useful)
            reach.append(MIRROR_REACH)
        turns = [i for i, u in enumerate(useful) if u.any()]
        if not turns:
            return []
        # only each frame's own worthwhile turns are posed, all at once, one row group
        # each: a frame's rows are those it would have alone
        which = torch.stack([useful[i] for i in turns])  # (turns, rows)
        turn, row = which.nonzero(as_tuple=True)
        params = {k: v[row] for k, v in rows.params.items()}
        goal = torch.stack([goals[i] for i in turns])[turn, row]

        distance = goal_distance(goal, BODY, 1e4)
        path = body.keypoint_path(params)
        limits = self.config.joint_limit_weight
        if path is not None:  # without autograd, as a keypoint stage
            objective = KeypointObjective(path, body.pose_group(), distance,
                                          np.ones((len(goal), 1), np.float32),
                                          {"joint_limits": limits},
                                          np.zeros(len(goal), np.float32), self._counted)
        else:
            def objective() -> Callable[[slice], torch.Tensor]:
                keypoints = body(params, vertices=False, spheres=False).keypoints
                value, slope = distance(keypoints)
                cost = (with_gradient(keypoints, value[:, 0], slope[:, 0])
                        + limits * body.joint_limits(params))
                return lambda r: cost[r].sum()

        self._minimise([params[n] for n in body.pose_group()], objective, "leg restart",
                       lbfgs.row_groups(len(goal), len(goal)), max_iter=MIRROR_ITERATIONS)
        with torch.no_grad():
            missed = (body(params, vertices=False).keypoints[:, BODY] - goal).norm(dim=-1)
        restarts = []
        for n, index in enumerate(turns):
            posed = turn == n
            within = torch.zeros(len(kp), dtype=torch.bool)
            within[row[posed]] = missed[posed].max(1).values < reach[index]
            tried = useful[index] & within
            if bool(tried.any()):
                turned = {k: v.detach().clone() for k, v in rows.params.items()}
                for k, v in params.items():
                    turned[k][row[posed]] = v[posed].detach()
                restarts.append((turned, tried))
        return restarts

    def _hidden_leg_postures(self, rows: _Rows, stage: Stage) -> _Rows:
        """``rows`` (one per frame), each frame whose detector reports no knee or ankle at HIDDEN
        or more and whose fitted knees lie in the image (legs behind furniture, or cut off by
        the image's edge where the fit brings the knees inside it; with
        ``hidden_legs_cut_off``, wherever they lie) replaced by the best of its
        fit and copies with the legs posed as each start posture's
        (:meth:`BodyModel.leg_postures`), ranked as the starts are: the ``stage``'s data term
        plus how badly each can meet the scene at its best scale (with the size prior there; the
        contact parts of ``hidden_leg_uncounted`` counted as missing, whatever they touch: a
        tall kneeler's legs posed sitting rested the thighs on the low table in front, nearer
        and smaller, and won). Hidden legs are the start's guess, which the keypoint stages keep
        and the scale search then places the body around (development seed 315's kneeler behind
        a low table, its knees fitted 55-61 cm off the floor: 264 -> 75 mm posed kneeling). With
        ``hidden_leg_refit``, each is first refitted through ``stage``
        (:meth:`_refit_candidates`). With ``hidden_shin_postures``, so are the frames whose
        knees the detector reports at HIDDEN or more and nothing below them (no ankle, toe or
        heel at HIDDEN), their fitted ankles in the image, with the shins alone posed, refitted
        without the plumb-shin prior (on for such legs, it would draw them back down): a
        kneeler's shins flat behind a low table and a squatter's upright project alike (seed
        102's squatter)."""
        detected = rows.detected
        legs = (detected[:, [*KNEES, *ANKLES]] < HIDDEN).all(1)
        shins = ((detected[:, KNEES] >= HIDDEN).all(1) & (detected[:, FEET] < HIDDEN).all(1)
                 & self.config.hidden_shin_postures)
        if not bool((legs | shins).any()):  # most frames: no variant built, no body posed
            return rows
        with torch.no_grad():
            joints = self.body(rows.params, vertices=False).keypoints
        if not self.config.hidden_legs_cut_off:
            legs &= self.camera.in_image(self.camera.project(joints[:, KNEES])).all(1)
        shins &= self.camera.in_image(self.camera.project(joints[:, ANKLES])).all(1)
        hidden = legs | shins
        postures = self.body.leg_postures(rows.params, thighs_kept=shins)
        if not bool(hidden.any()) or not postures:
            return rows
        names = ["fitted", *postures]
        tried = torch.stack([torch.ones_like(hidden), *[hidden] * len(postures)], 1)
        wide = rows.widened(list(postures.values())).taken(
            tried.flatten().nonzero().flatten().tolist())
        counts = tried.sum(1).tolist()
        if self.config.hidden_leg_refit:  # hidden shins' postures without the plumb prior
            for rows_of, plumb in ((legs, True), (shins, False)):
                if bool(rows_of.any()):
                    self._refit_candidates(wide, stage, torch.repeat_interleave(
                        rows_of, torch.tensor(counts)).nonzero().flatten(), plumb)
        with torch.no_grad():
            data = self._data_term(stage, self.body(wide.params, vertices=False),
                                   wide.target, wide.conf)
        best = self._best_rows(wide.params, wide.detected, {"data": data}, counts,
                               by_scene=True, priors=False, uncounted=self.hidden_leg_parts)
        for frame, (row, group) in enumerate(zip(best, lbfgs.sized_groups(counts))):
            if row != group.start:
                part = "shins" if shins[frame] else "legs"
                self.events.append(f"hidden {part} posed {names[row - group.start]}" + (
                    f" (frame {frame} of the batch)" if len(counts) > 1 else ""))
        return wide.taken(best)

    def _refit_candidates(self, rows: _Rows, stage: Stage, which: torch.Tensor,
                          plumb: bool = True) -> None:
        """The rows ``which`` (indices) of ``rows`` fitted through ``stage`` (root and
        body pose free, each row alone; without ``plumb``, no shin drawn toward hanging),
        in place: a posture set by hand is ranked at its own fit of the keypoints, not at
        the pose fitted for another (held-out seed 103's kneeler behind a low table: its
        kneeling legs, set, paid 1016 in data against the fitted legs' 652, the faint
        knees and ankles and the trunk fitted around the other legs; refitted, 577
        against 520, and kneeling won: 452 -> 155 mm)."""
        picked = rows.taken(which.tolist())
        free = ["transl", "global_orient", *self.body.pose_group()]
        self._run_stage(stage, picked.params, free, picked.target, picked.conf, picked.depth,
                        None, lbfgs.row_groups(len(which), len(which)), plumb)
        for name, value in picked.params.items():
            rows.params[name] = rows.params[name].index_copy(0, which, value)

    def _legs_onto_rays(self, kp: torch.Tensor, rows: _Rows, hip: int, knee: int,
                        foot: list[int]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Where the fit misses a leg's knee by more than KNEE_MISS px (the detector
        reported the knee and the ankle), the leg posed onto their camera rays from the
        hip, thigh and shin lengths kept: the knee at either point of its ray at the
        thigh's length from the hip, the ankle at either point of its ray at the shin's
        length from that knee, the foot carried along. Per such pose, the knee, ankle and
        foot (rows, 2 + feet, 3) and which rows are worth a restart ((rows,) bool). A
        kneeler's knee seen at low confidence otherwise stayed raised in front, the shin
        folded back to an ankle in the air, the keypoint's pull saturated."""
        ankle = foot[0]
        hips, knees_at, ankles_at = kp[:, hip], kp[:, knee], kp[:, ankle]
        knee_ray, ankle_ray = (self.camera.rays(rows.target[:, joint])
                               for joint in (knee, ankle))
        miss = (self.camera.project(knees_at) - rows.target[:, knee]).norm(dim=-1)
        knees, reach = ray_points_at(knee_ray, hips, (knees_at - hips).norm(dim=-1),
                                     KNEE_SLACK)
        worth = (rows.conf[:, knee] > 0) & (rows.conf[:, ankle] > 0) & (miss > KNEE_MISS)
        poses = []
        for k in range(2):
            ankles, reaches = ray_points_at(ankle_ray, knees[:, k],
                                            (ankles_at - knees_at).norm(dim=-1), KNEE_SLACK)
            for a in range(2):
                feet = kp[:, foot[1:]] + (ankles[:, a] - ankles_at)[:, None]
                poses.append((torch.cat([knees[:, k, None], ankles[:, a, None], feet], 1),
                              worth & reach[:, k] & reaches[:, a]))
        return poses

    def _announce(self, stage: str) -> None:
        if self.on_stage is not None:
            self.on_stage(stage)

    # ------------------------------------------------------------------ objective
    def _targets(self, frames: list[Frame]) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoint pixels (B, K, 2) and the detector's confidences (B, K) of the points
        the model defines; the data term also ignores ``config.ignore_keypoints``."""
        data = torch.tensor(np.stack([f.keypoints.data for f in frames]), dtype=torch.float32)
        return data[..., :2], data[..., 2] * self.body.keypoint_mask

    def _keypoint_weights(self, stage: Stage, conf: torch.Tensor) -> torch.Tensor:
        """(B, K) the data term's weight of each keypoint with confidences ``conf`` (B, K)
        in ``stage``: (its part's weight * confidence)^2, as in SMPLify-X."""
        w = stage.weights
        joint_weight = torch.zeros_like(conf)
        joint_weight[:, BODY] = w.get("body", 0)
        joint_weight[:, LEFT_HAND] = w.get("hands", 0)
        joint_weight[:, RIGHT_HAND] = w.get("hands", 0)
        joint_weight[:, FACE] = w.get("face", 0)
        return (joint_weight * conf) ** 2

    def _data_term(self, stage: Stage, out: BodyOutput, target: torch.Tensor,
                   conf: torch.Tensor) -> torch.Tensor:
        """The stage's weighted robust reprojection error (B,) of the keypoints ``target``
        (B, K, 2) with confidences ``conf`` (B, K)."""
        return keypoint_terms.keypoint_data(out.keypoints, self.camera, target,
                                            self._keypoint_weights(stage, conf),
                                            self.config.data_rho)

    def _held(self, stage: Stage, params: Params, conf: torch.Tensor, free: Sequence[str],
              plumb: bool = True) -> _Held:
        """What stays put while a stage runs (:class:`_Held`); without ``plumb``, no shin
        is drawn toward hanging."""
        w, cfg, body = stage.weights, self.config, self.body
        legs = cut_legs(conf) & plumb
        if cfg.plumb_cut_frames_only:
            legs = legs & nothing_below_knees(conf)[..., None]
        priors = {"pose_prior": (body.pose_prior, body.pose_group()),
                  "shape": (body.shape_prior, body.shape_group()),
                  "bending": (body.bending_prior, body.pose_group()),
                  "hand_prior": (body.hand_prior, ["hand_pose"])}
        priors = {name: (w[name] ** (2 if cfg.squared_priors else 1), prior, reads)
                  for name, (prior, reads) in priors.items() if w.get(name, 0) > 0}
        with torch.no_grad():
            fixed = {name: weight * prior(params) for name, (weight, prior, reads)
                     in priors.items() if not set(reads) & set(free)}
        return _Held(weights=self._keypoint_weights(stage, conf),
                     upright=cfg.upright_weight * ankle_seen(conf),
                     cut=legs.float() if bool(legs.any()) else None,  # None: the shins' 0
                     priors=priors, fixed=fixed)

    def _terms(self, stage: Stage, params: Params, target: torch.Tensor, conf: torch.Tensor,
               depth: list, previous: torch.Tensor | None, free: Sequence[str] = (),
               held: _Held | None = None) -> Callable[[BodyOutput], dict[str, torch.Tensor]]:
        """The weighted value (B,) of every active term of a stage, as a function of the
        posed body (``params``), with what stays put while it runs (``held``, worked out
        here if not given)."""
        w = stage.weights
        cfg, body = self.config, self.body
        held = held or self._held(stage, params, conf, free)

        def terms(out: BodyOutput) -> dict[str, torch.Tensor]:
            data, standing, lying, plumb = keypoint_terms.posed_terms(
                out.keypoints, self.camera, target, held.weights, cfg.data_rho, self.up,
                cfg.upright_rho, cfg.level_rho, held.cut)  # one kernel for the four
            values = {"data": data,
                      "joint_limits": cfg.joint_limit_weight * body.joint_limits(params)}
            for name, (weight, prior, _) in held.priors.items():
                values[name] = (held.fixed[name] if name in held.fixed
                                else weight * prior(params))
            if cfg.upright_weight > 0:
                values["upright"] = held.upright * standing
            if cfg.level_weight > 0:
                values["level"] = cfg.level_weight * lying
            if cfg.plumb_shin_weight > 0:
                values["plumb_shins"] = cfg.plumb_shin_weight * plumb
            if w.get("self_penetration", 0) > 0:
                values["self_penetration"] = (w["self_penetration"]
                                              * losses.self_penetration(out, body))
            if any(w.get(t, 0) > 0 for t in SCENE_TERMS):
                for name, (points, _, value, slope) in self._scene_slopes(
                        stage, self._scene_view(out).vertices).items():
                    values[name] = w[name] * with_gradient(points, value, slope)
            if w.get("depth", 0) > 0 and any(d is not None for d in depth):
                values["depth"] = w["depth"] * losses.depth_data(out, body, depth,
                                                                 cfg.depth_rho)
            if w.get("temporal", 0) > 0 and previous is not None:
                values["temporal"] = w["temporal"] * losses.temporal(
                    out, previous, cfg.temporal_about_root)
            return values
        return terms

    def _keypoint_objective(self, stage: Stage, params: Params, free: list[str],
                            target: torch.Tensor, held: _Held, previous: torch.Tensor | None
                            ) -> KeypointObjective | None:
        """The objective of a stage that reads only the keypoints, the pose and the scene
        terms' vertices, the shape held, worked out without autograd
        (:mod:`keypoint_objective`) with what stays put while it runs (``held``) and, given
        the ``previous`` frame's keypoints, the temporal term; None for any other stage,
        or a body model without a :meth:`BodyModel.keypoint_path`."""
        mesh = self._mesh_read(stage)
        if (any(stage.weights.get(t, 0) > 0 for t in GRAPH_TERMS if t not in SCENE_TERMS)
                or mesh is True or set(free) & set(self.body.shape_group())):
            return None
        path = self.body.keypoint_path(params, mesh or None)
        if path is None:
            return None
        cfg = self.config
        columns = torch.stack([torch.ones_like(held.upright),
                               held.upright * (cfg.upright_weight > 0),
                               torch.full_like(held.upright, max(cfg.level_weight, 0)),
                               torch.full_like(held.upright, max(cfg.plumb_shin_weight, 0))], 1)
        priors = {"joint_limits": cfg.joint_limit_weight} | {
            name: weight for name, (weight, _, _) in held.priors.items()
            if name not in held.fixed}
        fixed = sum(held.fixed.values(), torch.zeros(len(columns)))

        temporal = stage.weights.get("temporal", 0) if previous is not None else 0
        if temporal > 0:
            columns = torch.cat([columns, torch.full_like(columns[:, :1], temporal)], 1)

        def posed(keypoints: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            value, slope = keypoint_terms.posed_values(
                keypoints, self.camera, target, held.weights, cfg.data_rho, self.up,
                cfg.upright_rho, cfg.level_rho, held.cut)
            if temporal > 0:
                motion, motion_slope = losses.temporal_value_and_slope(
                    keypoints, previous, cfg.temporal_about_root)
                value = torch.cat([value, motion[:, None]], 1)
                slope = torch.cat([slope, motion_slope[:, None]], 1)
            return value, slope

        return KeypointObjective(path, free, posed, columns.float().numpy(), priors,
                                 fixed.float().numpy(), self._counted,
                                 self._scene_terms(stage) if mesh else None)

    def _scene_terms(self, stage: Stage
                     ) -> Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
        """A stage's scene terms as :meth:`_terms` weighs them, without autograd: the scene
        terms' vertices (B, V, 3) -> their sum (B,) and its gradient in them."""
        w = stage.weights

        def scene_terms(vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            total, slopes, read = vertices.new_zeros(len(vertices)), [], []
            for name, (_, ids, value, slope) in self._scene_slopes(stage, vertices).items():
                total += w[name] * value
                slopes.append(w[name] * slope)
                read.append(ids)
            if not slopes:
                return total, torch.zeros_like(vertices)
            return total, sum_into(torch.cat(slopes, 1), torch.cat(read), vertices.shape[1])
        return scene_terms

    def _scene_slopes(self, stage: Stage, vertices: torch.Tensor
                      ) -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                           torch.Tensor]]:
        """Each scene term the stage weighs, of the scene terms' vertices (B, V, 3),
        unweighted: the vertices it reads (picked, differentiable as ``vertices`` are), their
        indices, its value (B,) and its gradient in them (B, N, 3). Penetration: each vertex
        counted as many times as :func:`losses.penetration_vertices` says, tolerated as deep
        as its part may enter; contact: the contact vertices, touching as deep as they
        sink."""
        w, cfg, found = stage.weights, self.config, {}
        if w.get("penetration", 0) > 0:
            ids, counts = self.penetration_vertices
            points = picked(vertices, ids)
            found["penetration"] = (points, ids, *losses.penetration_value_and_slope(
                points, self.scene, self.penetration_tolerance, counts))
        if w.get("contact", 0) > 0 and self.contact_normals is not None:
            normals = self.contact_normals
            with torch.no_grad():  # the normals only choose which vertices qualify
                facing = normals(vertices)
            points = picked(vertices, normals.ids)
            found["contact"] = (points, normals.ids, *losses.contact_value_and_slope(
                points, facing, self.scene, cfg.contact_rho, cfg.contact_max_angle,
                cfg.contact_max_distance, self.contact_sink))
        return found

    def _run_stage(self, stage: Stage, params: Params, free: list[str], target: torch.Tensor,
                   conf: torch.Tensor, depth: list, previous: torch.Tensor | None,
                   groups: list[slice], plumb: bool = True) -> dict[str, torch.Tensor]:
        """L-BFGS calls on the ``free`` parameters until each frame's loss (its ``groups``
        of rows) settles; returns the terms at the accepted points (not at the line
        search's last probes). Without ``plumb``, no shin is drawn toward hanging. In a
        stage that poses the mesh (a row's evaluation costs about 1 ms), the frames still
        running go on over their own rows alone once others have settled."""
        mesh = self._mesh_read(stage)
        spheres = stage.weights.get("self_penetration", 0) > 0
        held = self._held(stage, params, conf, free, plumb)

        def terms_at(rows_params: Params, rows: torch.Tensor | None = None
                     ) -> Callable[[], dict[str, torch.Tensor]]:
            """The stage's terms at ``rows_params``, ``rows`` of the frames' (None: all)."""
            if rows is None:
                terms_of = self._terms(stage, rows_params, target, conf, depth, previous,
                                       free, held)
            else:
                terms_of = self._terms(
                    stage, rows_params, target[rows], conf[rows], [depth[r] for r in rows],
                    previous if previous is None or len(previous) == 1 else previous[rows],
                    free, self._held(stage, rows_params, conf[rows], free, plumb))
            return lambda: terms_of(self.body(rows_params, vertices=mesh, spheres=spheres))

        def objective_of(terms: Callable[[], dict[str, torch.Tensor]],
                         frames: torch.Tensor | None) -> lbfgs.Objective:
            def objective() -> Callable[[slice], torch.Tensor]:
                # the terms summed once for every row, then per group: each operation on
                # the way costs about 10 us forward and back, for some 600 evaluations
                total = _row_totals(list(terms().values()), frames)
                return lambda rows: total[rows].sum()
            return objective

        terms = terms_at(params)
        direct = self._keypoint_objective(stage, params, free, target, held, previous)
        expanded = (self.body.shape_expanded(params, mesh)
                    if set(self.body.shape_group()) & set(free)
                    else nullcontext(lambda rows: None))
        with expanded as narrow_shape:
            def narrow(rows: torch.Tensor) -> tuple[list[torch.Tensor], lbfgs.Objective]:
                kept = {k: v[rows].detach().clone() for k, v in params.items()}
                narrow_shape(rows)
                return ([kept[n].requires_grad_(True) for n in free],
                        objective_of(terms_at(kept, rows), kept.get(FRAME)))

            self._minimise([params[n] for n in free],
                           direct or objective_of(terms, params.get(FRAME)),
                           stage.name, groups, stage.max_iter,
                           stage.max_calls or self.config.max_calls, self.config.ftol,
                           None if direct else narrow)
        with torch.no_grad():
            return terms()

    def _mesh_read(self, stage: Stage) -> bool | VertexSubset:
        """What of the mesh a stage's terms read: none, the scene terms' vertices, or all."""
        read = {t for t in MESH_TERMS if stage.weights.get(t, 0) > 0}
        if read and read <= set(SCENE_TERMS) and self.scene_subset is not None:
            return self.scene_subset
        return bool(read)

    def _scene_view(self, out: BodyOutput) -> BodyOutput:
        """``out`` with the scene terms' vertices only (picked when the whole mesh was
        posed, for the depth term)."""
        if out.vertices.shape[1] == len(self.scene_subset.ids):
            return out
        return replace(out, vertices=out.vertices[:, self.scene_subset.ids])

    # ------------------------------------------------------------------ scene-aware depth
    @staticmethod
    def _scene_stage(stage: Stage) -> bool:
        return stage.weights.get("penetration", 0) > 0 or stage.weights.get("contact", 0) > 0

    def _scales_searched(self) -> bool:
        return self.config.scale_search and any(self._scene_stage(s) for s in self.config.stages)

    def _scale_search(self, params: Params, detected: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """Per body, the scale about the camera centre at which it best meets the scene
        with the joints the detector clearly saw (``detected`` (B, 25), its confidences)
        in view and the legs it reports faintly out of it, and that scale's cost (see
        :mod:`scale_search`)."""
        search, _ = self._scale_searcher(params, detected, self.config.scale_feet_carry)
        return search(torch.arange(len(detected)))

    def _scale_searcher(self, params: Params, detected: torch.Tensor, feet_carry: bool = False,
                        uncounted: torch.Tensor | None = None
                        ) -> tuple[Callable[..., tuple[torch.Tensor, torch.Tensor]],
                                   torch.Tensor]:
        """:meth:`_scale_search` of the bodies ``params`` posed once, searched for the
        ``rows`` asked, each under its total's ceiling where ``ceilings`` are given
        (:func:`scale_search.best_scale`), and the bodies' sizes as its size prior reads
        them (:meth:`_sizes`); with ``feet_carry``, bodies on their feet rest on them
        alone (:func:`scale_search.feet_carried`); the contact parts ``uncounted`` ((P,)
        bool for every body, or (B, P)) count as missing."""
        cfg, body = self.config, self.body
        with torch.no_grad():
            out = body(params)
            vertices = out.vertices
            normals = vertices.new_zeros(vertices.shape)
            normals[:, self.vertex_normals.ids] = self.vertex_normals(vertices)
        joints = out.keypoints[:, BODY]
        up = self.scene.up_in_camera()
        seen, faint = detected > SEEN, self._faint_legs(detected, joints)
        if cfg.scale_free_toe_rays:
            seen &= ~kneelers_toes(joints, up)
        seen = [joints[b, seen[b]] for b in range(len(joints))]
        faint = [joints[b, faint[b]] for b in range(len(joints))]
        axes = out.spheres[..., :3] if cfg.scale_axes and out.spheres is not None else None
        counted = (standing_counts(standing_legs(joints, detected, up), self.standing_parts)
                   if bool(self.standing_parts.any()) and cfg.scale_standing_feet else None)
        if uncounted is not None and bool(uncounted.any()):
            counted = (torch.ones(len(joints), uncounted.shape[-1], dtype=torch.bool)
                       if counted is None else counted) & ~uncounted
        sizes = self._sizes(params)
        feet = feet_carried(joints, detected, up) if feet_carry else None
        sinks = cfg.lying_sink * lying(joints, up, cfg.level_rho) if cfg.lying_sink else None

        def search(rows: torch.Tensor, ceilings: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
            return best_scale(vertices[rows], normals[rows], body.scene_vertices, self.carrying,
                              self.contact_part_ids, self.scene, cfg.uses("contact"),
                              cfg.uses("penetration"), cfg.contact_rho, cfg.contact_max_angle,
                              cfg.contact_max_distance, cfg.scale_support,
                              [seen[r] for r in rows] if cfg.scale_visibility else None,
                              self.toes, None if axes is None else axes[rows],
                              [faint[r] for r in rows] if cfg.scale_faint_legs else None,
                              ceilings, None if counted is None else counted[rows],
                              sizes[rows], None if feet is None else feet[rows],
                              None if sinks is None else sinks[rows],
                              size_weight=self._size_weight())
        return search, sizes

    def _sizes(self, params: Params) -> torch.Tensor:
        """(B,) each body's size as the scale search's size prior reads it
        (:func:`scale_search.size_prior`): over the prior-mean body's, whose size the
        keypoint stages of a fit from scratch hold, or over that of the fit's ``sized_as``
        body (sequence mode: the anchor's; a person's size does not change between frames,
        and a prior centred on the neighbour's size let each frame's search move it on:
        development seed 311's lying body grew from 6 % to 17 % over the truth's stature
        in five frames)."""
        sizes = self.body.relative_size(params)
        return sizes if self._size_unit is None else sizes / self._size_unit

    def _size_weight(self) -> float:
        """The size prior's weight: a population's about the prior-mean body's size, or,
        in sequence mode, a chain's about its anchor's (see FitConfig.scale_size_weight)."""
        cfg = self.config
        return cfg.scale_size_weight if self._size_unit is None else cfg.sequence_size_weight

    def _faint_legs(self, detected: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """(..., 25) bool: the knees and ankles the detector reports under HIDDEN
        (``detected`` (..., 25)) whose fitted joints (``joints`` (..., 25, 3), camera
        frame) project into the image: a leg cut off by the image's edge is not hidden."""
        legs = torch.zeros(detected.shape[-1], dtype=torch.bool)
        legs[[*KNEES, *ANKLES]] = True
        return legs & (detected < HIDDEN) & self.camera.in_image(self.camera.project(joints))

    def _pointed_feet(self, params: Params, seen: torch.Tensor) -> Params:
        """``params`` with the unseen feet of kneeling legs pointed along the shins (see
        :data:`scale_search.FLAT_SHIN`)."""
        with torch.no_grad():
            keypoints = self.body(params, vertices=False).keypoints[:, BODY]
        which = unseen_feet_on_kneeling_legs(keypoints, seen, self.scene.up_in_camera())
        return self.body.point_feet(params, which) if bool(which.any()) else params

    def _lifted_feet(self, params: Params, seen: torch.Tensor) -> Params:
        """``params`` with each foot none of whose toes is ``seen`` ((B, 25) bool) and
        whose toes sink more than SUNK_TOES into the scene turned toward its neutral
        ankle (toes at right angles to the shin): by the least of LIFT_KEPT's turns that
        brings them within SUNK_TOES, or else the one that sinks them least, where that
        lifts them by LIFT_MIN. Unseen toes are the pose prior's and the start's guess; a
        foot 5-7 cm deep in the floor is pulled out by the scene stages' first steps
        turning and bending the whole body, and the scene guard then undoes them,
        penetration and all (held-out seed 103's leg-up sitter: 9-11 % of the body more
        than 1 cm inside the scan in four frames). A foot already near its neutral ankle
        is left to the scene stages (held-out seed 104's reacher, its foot turned 2
        degrees, ended 10 cm over the floor and was refitted from its other start, 71 ->
        176 mm). Fits from scratch only: a warm-started frame's feet are its neighbour's,
        which the scene stages placed."""
        unseen = toes_unseen(seen)  # (B, 2) right, left
        if not bool(unseen.any()):
            return params

        def sunk(p: Params) -> torch.Tensor:  # (B, 2) deepest toe vertex, per foot
            with torch.no_grad():
                vertices = self.body(p, vertices=self.toe_subset, spheres=False).vertices
            return torch.stack([torch.relu(-self.scene.signed_distance(
                vertices[:, toes])).amax(1) for toes in self.toe_sides], 1)

        depth = sunk(params)
        which = unseen & (depth > SUNK_TOES)
        if not bool(which.any()):
            return params
        kept = torch.tensor(LIFT_KEPT)
        # every share for every body (share-major rows), posed in one evaluation
        repeated = {k: v.repeat(len(kept), *[1] * (v.dim() - 1)) for k, v in params.items()}
        shares = kept.repeat_interleave(len(depth))[:, None]
        tried = self.body.relax_feet(repeated, torch.where(which.repeat(len(kept), 1),
                                                           shares, 1.0))
        depths = sunk(tried).view(len(kept), *depth.shape)  # (shares, B, 2)
        first = (depths <= SUNK_TOES).float().argmax(0)  # the first share that holds
        share = torch.where((depths <= SUNK_TOES).any(0), first, depths.argmin(0))
        lifted = which & (depths.gather(0, share[None])[0] <= depth - LIFT_MIN)
        if not bool(lifted.any()):
            return params
        self.events.append("toes sunk in the scene: the " + " and ".join(
            f"{side} foot" for side, any_ in zip(("right", "left"), lifted.any(0)) if any_)
            + " turned toward its neutral ankle")
        return self.body.relax_feet(params, torch.where(lifted, kept[share], 1.0))

    def _depth_scale(self, params: Params, depth: list) -> torch.Tensor:
        """Per body, the scale about the camera centre that puts its camera-facing surface
        at the depth cloud's distance (medians; 1 without a cloud): the depth term is
        robust to a few centimetres and barely pulls a body that the keypoints put 20-40 cm
        off."""
        with torch.no_grad():
            vertices = self.body(params).vertices
            seen = losses.facing_camera(vertices, self.body)
        scale = torch.ones(len(vertices))
        for b, cloud in enumerate(depth):
            if cloud is not None and len(cloud):
                scale[b] = cloud.norm(dim=1).median() / vertices[b, seen[b]].norm(dim=1).median()
        return scale

    def _rescale(self, params: Params, scale: torch.Tensor, frames: int) -> None:
        """Scale each body about the camera centre by ``scale``, which keeps its
        projection: its shape, root turn and translation refitted to its scaled keypoints
        (:func:`rescale.rescaled`), in place, without skinning the mesh (the scene stages
        that follow refit the shape to the scene); a frame none of whose bodies moves by
        1 % is left as it is, and not posed. Each body is rescaled alone, so alike in any
        batch."""
        moved = [rows for rows in lbfgs.row_groups(len(scale), frames)
                 if bool(((scale[rows] - 1).abs() >= 0.01).any())]
        if not moved:
            return
        rows, _ = lbfgs.packed(moved)
        fitted = rescaled(self.body, {k: v[rows] for k, v in params.items()}, scale[rows])
        for name, value in fitted.items():
            params[name][rows] = value

    def _minimise(self, variables: list[torch.Tensor],
                  objective: lbfgs.Objective | lbfgs.Direct,
                  step: str, groups: list[slice], max_iter: int | None = None,
                  max_calls: int = 1, ftol: float | None = None,
                  narrow: lbfgs.Narrow | None = None) -> None:
        """L-BFGS on ``variables``, in place, each group of rows (a frame's) on its own
        (:mod:`lbfgs`): up to ``max_calls`` calls, stopped early when a call changes the
        group's loss by at most ``ftol`` of it. A call that ends on non-finite values is
        undone, ends the group's step and is recorded in :attr:`events`. With ``narrow``,
        the groups still running go on over their own rows alone once others end."""
        for v in variables:
            v.requires_grad_(True)
        failed = lbfgs.minimise(variables, objective, groups,
                                max_iter or self.config.max_iter, max_calls, ftol,
                                narrow=narrow)
        for v in variables:
            v.requires_grad_(False)
        if any(failed):
            self.events.append(f"{step}: non-finite values, last step undone")

    # ------------------------------------------------------------------ initialisation
    def initialise(self, frames: list[Frame], as_detected: list[bool] | None = None
                   ) -> tuple[Params, list[tuple[str, ...]]]:
        """The starting body of each frame (:func:`initialisation.best_start`), upright
        with respect to the scene's world up (without a scene, the camera's -y), from the
        detector's confidences (neck and hips included, unlike the data term); and per
        frame the parts whose left and right the detector most likely exchanged (with
        ``config.swap_sides``, except in the frames ``as_detected``). The same frames as
        last time get the same answer without the search: sequence mode's anchor search,
        then its fit, and a fit from the other start ask for a frame's starts twice
        running."""
        as_detected = as_detected or [False] * len(frames)
        seen, fixed, params, labels, events = self._started
        keypoints = [f.keypoints.data for f in frames]
        if (len(seen) == len(keypoints) and fixed == as_detected
                and all(map(np.array_equal, seen, keypoints))):
            self.events += events
            return {k: v.clone() for k, v in params.items()}, list(labels)
        before = len(self.events)
        target, conf = self._targets(frames)
        keep = self.config.start_candidates
        single = [fixed or not self.config.swap_sides for fixed in as_detected]
        params, labels = {}, [()] * (len(frames) * keep)
        for kind in sorted(set(single)):  # frames searched under one labelling, or every
            which = [b for b, s in enumerate(single) if s == kind]
            labellings = LABELLINGS[:1] if kind else LABELLINGS
            found, chosen = best_start(
                self.body, self.camera, target[which], conf[which], self.up,
                self.config.data_rho, self.config.init_depth_weight,
                [side_swap(label) for label in labellings], events=self.events, keep=keep,
                facing_cost=self.config.facing_cost,
                guessed_legs=self._guessed_legs(conf[which]))
            rows = [b * keep + r for b in which for r in range(keep)]  # in frame order
            for name, value in found.items():
                params.setdefault(name, value.new_empty(len(labels), *value.shape[1:]))
                params[name][rows] = value
            for row, c in zip(rows, chosen):
                labels[row] = labellings[int(c)]
        self._started = ([k.copy() for k in keypoints], list(as_detected),
                         {k: v.clone() for k, v in params.items()}, labels,
                         self.events[before:])
        return params, list(labels)

    def _guessed_legs(self, conf: torch.Tensor) -> torch.Tensor | None:
        """(B,) bool: the frames whose keypoints (the detector's confidences ``conf``
        (B, K)) cannot tell sitting from standing, whose second start has the other
        thighs (``config.start_other_thighs``): no ankle seen, or (with
        ``start_thighs_hidden``) neither hip nor knee; None without."""
        if not self.config.start_other_thighs:
            return None
        guessed = ~ankle_seen(conf)
        return guessed | thighs_hidden(conf) if self.config.start_thighs_hidden else guessed

    def _closest_labelling(self, target: torch.Tensor, conf: torch.Tensor,
                           previous: torch.Tensor | None) -> list[tuple[str, ...]]:
        """Sequence mode: per frame the labelling whose body keypoints lie closest (robust
        pixel distance) to the previous fit's, so that a swap does not flip the body."""
        if not self.config.swap_sides or previous is None:
            return [()] * len(target)
        labellings = LABELLINGS
        projected = self.camera.project(previous[:, BODY])  # (1 or B, 25, 2)
        costs = []
        for label in labellings:
            order = side_swap(label)
            squared = ((target[:, order][:, BODY] - projected) ** 2).sum(-1)
            costs.append((conf[:, order][:, BODY] ** 2 * losses.gmof(
                squared, self.config.data_rho)).sum(1))
        best = torch.stack(costs).argmin(0)
        return [labellings[int(b)] for b in best]


def _row_totals(terms: list[torch.Tensor], frames: torch.Tensor | None) -> torch.Tensor:
    """(B,) the sum of the terms (each (B,)) of each row, ``frames`` (B,) the rows' frames:
    a sum down a column of (terms, rows) runs in another order for one row than for
    several, so each frame's rows are summed as the frame alone would have them (one row
    a frame: along each row, which sums as one row's column does)."""
    if not one_frame(frames) and len(frames.unique()) == len(frames):
        return torch.stack(terms, 1).sum(1)
    return by_frame(lambda values: values.T.sum(0), frames, torch.stack(terms).T)
