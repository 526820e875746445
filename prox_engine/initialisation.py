"""Starting bodies for a fit: each starting posture of the body model in a set of root
orientations (upright and turned about world up, or lying on the back, a side or the front
with the head toward any horizontal direction), each moved rigidly (root rotation and
translation only) onto the keypoints; per frame the candidates that explain the body
keypoints best are kept (the best, or the few best distinct ones, which the fitter then
fits side by side to choose between them).

Moving a posture rigidly moves its keypoints rigidly, so every candidate is fitted from one
evaluation of the body per posture: hundreds of candidates cost less than one body stage.
Depth comes from similar triangles on the torso, foreshortened as the candidate's
orientation foreshortens it, and is held softly while the candidate turns (SMPLify-X's
camera stage, generalised to any orientation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import torch

from . import lbfgs
from .body.base import BodyModel, Params
from .camera import Camera
from .geometry import axis_angle_to_matrix, matrix_to_axis_angle
from .keypoint_terms import keypoint_data
from .keypoints import BODY, TORSO_EDGES
from .rigid_terms import rigid_fit

TORSO = [1, 2, 5, 8, 9, 12]  # neck, shoulders, mid-hip, hips: nearly rigid in any posture
LIMB_WEIGHT = 0.25  # the other body keypoints guide the rigid fit less than the torso
UPRIGHT_TURNS = 4  # upright candidates: facing the camera, then turned by 90 degrees each
LYING_TURNS = 8  # lying candidates: head toward each of 8 horizontal directions
# Candidates are compared by their robust reprojection error with this scale (px): a wrong
# posture is 50-150 px off at a few metres, noise and a detector's offsets 5-20 px.
SCORE_RHO = 50.0
# What a relabelling must gain (robust px^2 at SCORE_RHO, confidence-weighted) before the
# keypoints are taken to have their sides swapped.
SWAP_COST = 500.0  # on the tuning seed: 41 of 42 frames labelled right, no false swap
# Cost (as many px^2 of data) of the cosine between body up and world up moving by 1: a
# candidate may lean 30 degrees for about 200 px^2, but not turn from lying to upright.
TILT_WEIGHT = 1e4
DISTINCT_TURN = math.radians(45)  # starts kept side by side differ at least this much
# A detector finds the nose and eyes confidently only in a face it sees (seen from behind
# OpenPose reports them faintly or not at all): above this mean confidence the person is
# taken to face the camera (best_start's ``facing_cost``).
FACE, FACE_SEEN = [0, 15, 16], 0.5


@dataclass
class Candidates:
    """Starting postures and root rotations (model frame to camera frame)."""

    postures: list[str]  # (C,)
    rotations: torch.Tensor  # (C, 3, 3)


def candidates(body: BodyModel, up: torch.Tensor) -> Candidates:
    """Every posture upright and turned about ``up`` (world up in camera coordinates);
    the body's lying postures also on the back, each side and the front."""
    view = torch.tensor([0.0, 0.0, 1.0])
    toward = -(view - (view @ up) * up)  # horizontal direction toward the camera
    if toward.norm() < 1e-3:  # looking straight down or up
        toward = torch.tensor([0.0, 1.0, 0.0]) - up[1] * up
    toward = toward / toward.norm()
    side = torch.linalg.cross(up, toward)

    def horizontal(angle: float) -> torch.Tensor:
        return math.cos(angle) * toward + math.sin(angle) * side

    def turns(count: int) -> list[torch.Tensor]:
        return [horizontal(2 * math.pi * i / count) for i in range(count)]

    postures, frames = [], []  # frames: the model's (forward, up) in camera coordinates
    for posture in body.postures:
        if posture in body.lying_postures:
            for head in turns(LYING_TURNS):
                across = torch.linalg.cross(up, head)
                for forward in (up, across, -across, -up):  # back, sides, front
                    postures.append(posture)
                    frames.append((forward, head))
        else:
            for forward in turns(UPRIGHT_TURNS):
                postures.append(posture)
                frames.append((forward, up))
    model_f, model_u = body.forward_axis(), body.up_axis()
    src = torch.stack([model_f, model_u, torch.linalg.cross(model_f, model_u)], 1)
    rotations = torch.stack([torch.stack([f, u, torch.linalg.cross(f, u)], 1) @ src.T
                             for f, u in frames])
    return Candidates(postures, rotations)


def best_start(body: BodyModel, camera: Camera, target: torch.Tensor, conf: torch.Tensor,
               up: torch.Tensor, rho: float, depth_weight: float,
               labellings: Sequence[list[int]] = (), max_iter: int = 30,
               events: list[str] | None = None, keep: int = 1, facing_cost: float = 0.0,
               guessed_legs: torch.Tensor | None = None) -> tuple[Params, torch.Tensor]:
    """Parameters of the ``keep`` best distinct rigidly fitted candidates of each frame
    (B * keep rows, frame-major, best first; see :func:`_distinct`), and which of
    ``labellings`` (row orders of the keypoints, e.g. with the legs' sides exchanged; none:
    the keypoints as given) each explains the keypoints under, (B * keep,). ``target``
    (B, K, 2) pixels and ``conf`` (B, K) the detector's confidences. Where the detector
    sees the face, a start turned away from the camera costs up to ``facing_cost`` (as
    many px^2 of reprojection error). In the frames ``guessed_legs`` ((B,) bool: whose
    keypoints cannot tell sitting from standing) the second start is the best whose
    thighs differ from the best's (see :func:`_distinct`)."""
    orders = list(labellings) or [list(range(target.shape[1]))]
    frames, views = target.shape[0], len(orders)
    # Every frame under every labelling: (B, L) flattened to B * L "frames" below.
    target = torch.stack([target[:, o] for o in orders], 1).flatten(0, 1)
    conf = torch.stack([conf[:, o] for o in orders], 1).flatten(0, 1)
    batch = target.shape[0]
    cands = candidates(body, up)
    names = sorted(set(cands.postures))
    rest = {}
    for name in names:
        params = body.init_params(1, name)
        with torch.no_grad():
            rest[name] = (body(params, vertices=False).keypoints[0, BODY],
                          body.root_pivot(params)[0])
    kp0 = torch.stack([rest[p][0] for p in cands.postures])  # (C, 25, 3)
    thighs = {name: _thighs_forward(rest[name][0]) for name in names}
    seated = [thighs[p] for p in cands.postures]
    pivot = torch.stack([rest[p][1] for p in cands.postures])  # (C, 3)
    count = len(cands.postures)

    tgt, seen = target[:, BODY], conf[:, BODY]
    centre_w = _centre_weights(seen, events)  # (B, 25)
    fit_w = seen ** 2 * LIMB_WEIGHT
    fit_w[:, TORSO] = seen[:, TORSO] ** 2
    # Everything (B, C, ...) flattened to (B * C, ...).
    rot0 = cands.rotations.repeat(batch, 1, 1)
    kp = kp0.repeat(batch, 1, 1) - pivot.repeat(batch, 1)[:, None]
    w_c = centre_w.repeat_interleave(count, 0)
    flat_target = tgt.repeat_interleave(count, 0)
    flat_seen = seen.repeat_interleave(count, 0)
    flat_w = fit_w.repeat_interleave(count, 0)
    centre_px = torch.einsum("nk,nkd->nd", w_c, flat_target)
    turn = torch.zeros(batch * count, 3)
    model_up = body.up_axis()
    tilt0 = (rot0 @ model_up) @ up  # each candidate keeps its lean: lying stays lying
    transl = torch.zeros(batch * count, 3)

    def rotation() -> torch.Tensor:
        """Each candidate's orientation: its start's, turned by ``turn``."""
        return axis_angle_to_matrix(turn) @ rot0

    def rotated(turned: torch.Tensor) -> torch.Tensor:
        return kp @ turned.transpose(1, 2)

    # Two rounds: a candidate turns about world up (and leans a little) in the first, and
    # its similar-triangles depth follows its new orientation in the second. Each frame's
    # candidates are fitted on their own (lbfgs), so a frame starts alike in any batch.
    for _ in range(2):
        with torch.no_grad():
            posed = rotated(rotation())
            depth = _depth(camera, posed, flat_target, flat_seen, centre_px)
            ray = camera.backproject(centre_px[:, 0], centre_px[:, 1], depth)
            transl = ray - torch.einsum("nk,nkd->nd", w_c, posed)
        turn.requires_grad_(True)
        transl.requires_grad_(True)

        def objective() -> Callable[[slice], torch.Tensor]:
            loss = rigid_fit(turn, transl, rot0, kp, camera, flat_target, flat_w, w_c, depth,
                             tilt0, model_up, up, rho, depth_weight, TILT_WEIGHT)
            return lambda rows: loss[rows].sum()

        failed = lbfgs.minimise([turn, transl], objective, lbfgs.row_groups(batch * count, frames),
                                max_iter)
        turn.requires_grad_(False)
        transl.requires_grad_(False)
        if any(failed) and events is not None:
            events.append("initialise: non-finite values in the rigid fit, undone")
    with torch.no_grad():
        turned = rotation()
        score = keypoint_data(rotated(turned) + transl[:, None], camera, flat_target,
                              flat_seen ** 2, SCORE_RHO).view(batch, count)
        score = score + facing_cost * _turned_away(turned @ body.forward_axis(), transl,
                                                   conf).view(batch, count)
        score = torch.nan_to_num(score, nan=math.inf).view(frames, views, count)
        score[:, 1:] += SWAP_COST  # a detector swaps sides in a minority of frames
        score = score.flatten(1)  # over labellings and candidates
        chosen, starts = [], []
        for b in range(frames):
            rows = turned.view(frames, -1, 3, 3)[b]
            legs_guessed = guessed_legs is not None and bool(guessed_legs[b])
            for pick in _distinct(score[b], rows, cands.postures, keep,
                                  seated if legs_guessed else None):
                n = b * views * count + pick  # row of (frame, labelling, candidate)
                c = pick % count
                params = body.init_params(1, cands.postures[c])
                params["global_orient"] = matrix_to_axis_angle(turned[n:n + 1])
                # The body puts its rest keypoints at R (k - pivot) + pivot + transl.
                params["transl"] = (transl[n] - pivot[c])[None]
                starts.append(params)
                chosen.append(pick // count)
    return ({k: torch.cat([p[k] for p in starts]) for k in starts[0]}, torch.tensor(chosen))


def _distinct(score: torch.Tensor, rotation: torch.Tensor, postures: list[str], keep: int,
              seated: list[bool] | None = None) -> list[int]:
    """Indices of the ``keep`` best of one frame's scored (labelling, candidate) rows that
    differ from every better one kept in labelling, posture, or by more than
    DISTINCT_TURN in root rotation (the rigid fits of neighbouring candidates often end
    together); the best repeated when fewer are distinct. Given ``seated`` (per
    candidate: thighs bent forward from the trunk), the second is the best whose thighs
    differ from the best's: with the legs unseen the keypoints cannot tell a seated body
    from a standing one, the scene can."""
    count = len(postures)
    order = score.argsort().tolist()
    if seated is not None and keep > 1 and math.isfinite(float(score[order[0]])):
        other = [i for i in order if seated[i % count] != seated[order[0] % count]
                 and math.isfinite(float(score[i]))]
        if other:
            order = [order[0], other[0]] + [i for i in order[1:] if i != other[0]]

    def same(i: int, j: int) -> bool:
        return (i // count == j // count and postures[i % count] == postures[j % count]
                and _turn(rotation[i], rotation[j]) < DISTINCT_TURN)

    picked: list[int] = []
    for i in order:
        if len(picked) == keep or not math.isfinite(float(score[i])):
            break
        if not any(same(i, j) for j in picked):
            picked.append(i)
    picked = picked or [int(score.argmin())]
    return picked + picked[:1] * (keep - len(picked))


def _thighs_forward(keypoints: torch.Tensor) -> bool:
    """Whether a posture's thighs (hip to knee, BODY_25 ``keypoints`` (25, 3)) bend
    forward from its trunk (mid-hip to neck) by more than 45 degrees: sitting and
    crouching, not standing, kneeling or lying."""
    trunk = keypoints[1] - keypoints[8]
    thighs = keypoints[[10, 13]] - keypoints[[9, 12]]
    cos = (thighs @ trunk) / (thighs.norm(dim=1) * trunk.norm())
    return bool(cos.mean() > -math.cos(math.radians(45)))


def _turn(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (rad) of the rotation taking ``a`` to ``b``."""
    cos = ((a.T @ b).trace() - 1) / 2
    return math.acos(max(-1.0, min(1.0, float(cos))))


def _turned_away(forward: torch.Tensor, position: torch.Tensor, conf: torch.Tensor
                 ) -> torch.Tensor:
    """(B * C,) how far each candidate (``forward`` (B * C, 3) its facing, ``position`` a
    point of it, camera coordinates) turns its back to the camera, 0 (facing it or side on)
    to 1 (straight away), in the frames (``conf`` (B, K)) where the face is seen; else 0."""
    seen = (conf[:, FACE].mean(1) > FACE_SEEN).float()  # (B,)
    away = (forward * torch.nn.functional.normalize(position, dim=1)).sum(1).clamp_min(0)
    return away * seen.repeat_interleave(len(forward) // len(conf))


def _centre_weights(seen: torch.Tensor, events: list[str] | None) -> torch.Tensor:
    """(B, 25) weights summing to one over the seen torso points, else over every seen body
    keypoint, else all body keypoints alike (nothing seen)."""
    torso = torch.zeros_like(seen)
    torso[:, TORSO] = seen[:, TORSO]
    weights = torch.where(torso.sum(1, keepdim=True) > 0, torso, seen.clone())
    unseen = weights.sum(1) <= 0
    if bool(unseen.any()):
        if events is not None:
            events.append("initialise: no body keypoint seen")
        weights[unseen] = 1.0
    return weights / weights.sum(1, keepdim=True)


def _depth(camera: Camera, posed: torch.Tensor, target: torch.Tensor, seen: torch.Tensor,
           centre_px: torch.Tensor) -> torch.Tensor:
    """Similar-triangles depth (N,) of each candidate: f * projected 3D torso edge / 2D
    torso edge, each a mean over the edges weighted by their end points' confidences, the
    3D edges foreshortened across the viewing ray as the candidate's orientation makes
    them; the shoulder width when no torso edge is seen, 3 m when nothing is."""
    ray = camera.rays(centre_px)
    i, j = (torch.tensor(side) for side in zip(*TORSO_EDGES))
    weight = seen[:, i] * seen[:, j]  # (N, E)
    shoulders = seen[:, 2] * seen[:, 5]
    use_shoulders = (weight.sum(1) <= 0)[:, None]
    i = torch.where(use_shoulders, torch.tensor(2), i)
    j = torch.where(use_shoulders, torch.tensor(5), j)
    weight = torch.where(use_shoulders, shoulders[:, None], weight)
    rows = torch.arange(len(posed))[:, None]
    e3 = posed[rows, i] - posed[rows, j]  # (N, E, 3)
    across = (e3 - (e3 * ray[:, None]).sum(-1, keepdim=True) * ray[:, None]).norm(dim=-1)
    e2 = (target[rows, i] - target[rows, j]).norm(dim=-1)
    total = weight.sum(1)
    ok = (total > 0) & ((weight * e2).sum(1) > 1e-3 * total.clamp_min(1e-9))
    depth = camera.fx * (weight * across).sum(1) / (weight * e2).sum(1).clamp_min(1e-9)
    return torch.where(ok, depth, torch.full_like(depth, 3.0)).clamp(0.3, 30.0)
