"""Per-frame statistics of a fit: penetration, contact, reprojection error. Distances come
from the scene's triangles (:meth:`Scene.exact_signed_distance`), not from its SDF grid, so
that furniture thinner than a voxel is seen, wherever a vertex can be inside or touching."""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from .body.base import BodyModel
from .camera import Camera
from .keypoints import BODY, LIMBS, Keypoints, side_swap
from .scene import Scene

PENETRATION_THRESHOLD = 0.01  # a vertex "penetrates" when more than 1 cm inside
CONTACT_THRESHOLD = 0.02  # a part "touches" when one of its vertices is within 2 cm


def _penetration(d: torch.Tensor) -> dict:
    """Statistics of the signed distances ``d`` of the scene-relevant body vertices."""
    inside = d < -PENETRATION_THRESHOLD
    depth = torch.relu(-d)
    return {
        "penetrating_share": float(inside.float().mean()),
        "max_depth_m": float(depth.max()),
        "mean_depth_m": float(depth[inside].mean()) if inside.any() else 0.0,
    }


@torch.no_grad()
def penetration_stats(vertices: torch.Tensor, body: BodyModel, scene: Scene) -> dict:
    """Share of body vertices more than 1 cm inside the scene, their mean and the max depth."""
    return _penetration(scene.exact_signed_distance(vertices[body.scene_vertices]))


@torch.no_grad()
def touching_vertices(vertices: torch.Tensor, body: BodyModel, scene: Scene
                      ) -> dict[str, torch.Tensor]:
    """Per contact part, its vertices within 2 cm of the scene surface (or inside it)."""
    return _touching(_distances(vertices, scene, _contact_ids(body)), body)


def _contact_ids(body: BodyModel) -> torch.Tensor:
    return torch.cat(list(body.contact_parts.values()))


def _distances(vertices: torch.Tensor, scene: Scene, ids: torch.Tensor) -> torch.Tensor:
    """(V,) signed distances of the vertices ``ids`` (each once), NaN elsewhere: exact
    wherever a vertex can be inside the scene or touch it; the SDF grid's where it puts the
    vertex so far out that it cannot (beyond the contact threshold by twice a voxel's
    diagonal, more than its trilinear reading can be off), which every statistic here
    counts as the exact distance would, without the exact search's slowest queries."""
    ids = ids.unique()
    distance = torch.full((len(vertices),), float("nan"))
    points = vertices[ids]
    grid = scene.signed_distance(points)
    far = grid > CONTACT_THRESHOLD + 2 * math.sqrt(3) * scene.sdf.voxel_size
    distance[ids[far]] = grid[far]
    distance[ids[~far]] = scene.exact_signed_distance(points[~far])
    return distance


def _touching(distance: torch.Tensor, body: BodyModel) -> dict[str, torch.Tensor]:
    """:func:`touching_vertices` from the vertices' ``distance`` (V,) (:func:`_distances`)."""
    return {part: ids[distance[ids] < CONTACT_THRESHOLD]
            for part, ids in body.contact_parts.items()}


def contact_parts(vertices: torch.Tensor, body: BodyModel, scene: Scene) -> list[str]:
    """Contact parts with a vertex touching the scene (see :func:`touching_vertices`)."""
    return [p for p, ids in touching_vertices(vertices, body, scene).items() if len(ids)]


@torch.no_grad()
def scene_stats(vertices: torch.Tensor, body: BodyModel, scene: Scene
                ) -> tuple[dict, dict[str, list[int]]]:
    """One fit's penetration statistics and touching parts (as :func:`penetration_stats`
    and :func:`contact_parts`), and the vertex ids behind them, which renders paint; each
    scene query is made once."""
    ids = torch.nonzero(body.scene_vertices).flatten()
    distance = _distances(vertices, scene, torch.cat([ids, _contact_ids(body)]))
    d = distance[ids]
    touching = _touching(distance, body)
    stats = {**_penetration(d), "contact_parts": [p for p, t in touching.items() if len(t)]}
    flagged = {"penetrating": ids[d < -PENETRATION_THRESHOLD].tolist(),
               "contact": sorted(set(torch.cat(list(touching.values())).tolist()))}
    return stats, flagged


@torch.no_grad()
def keypoint_errors(keypoints3d: torch.Tensor, keypoints: Keypoints, camera: Camera,
                    mask: torch.Tensor, swapped: Sequence[str] = (),
                    min_confidence: float = 0.1) -> torch.Tensor:
    """(25,) pixel distance of each body keypoint from its detection, NaN where it was not
    detected with some confidence, with the left and right of the parts the fit found
    ``swapped`` exchanged (as it fitted them: a fit that rightly undid a leg swap is
    otherwise reported tens of pixels off)."""
    uv = camera.project(keypoints3d[BODY])
    target = torch.as_tensor(keypoints.data[side_swap(tuple(swapped))][BODY],
                             dtype=torch.float32)
    valid = (target[:, 2] > min_confidence) & mask[BODY]
    errors = (uv - target[:, :2]).norm(dim=-1)
    return torch.where(valid, errors, torch.full_like(errors, float("nan")))


def reprojection_error(keypoints3d: torch.Tensor, keypoints: Keypoints, camera: Camera,
                       mask: torch.Tensor, swapped: Sequence[str] = (),
                       min_confidence: float = 0.1) -> float:
    """Mean pixel distance over the body keypoints detected with some confidence (see
    :func:`keypoint_errors`); NaN where none was."""
    return float(keypoint_errors(keypoints3d, keypoints, camera, mask, swapped,
                                 min_confidence).nanmean())


def limb_errors(errors: torch.Tensor) -> dict[str, float]:
    """Per limb (keypoints.LIMBS) with a detected keypoint, the mean pixel distance of its
    detected keypoints from the fit, given each keypoint's ``errors`` (25,)
    (:func:`keypoint_errors`)."""
    means = {name: errors[list(rows)].nanmean() for name, rows in LIMBS.items()}
    return {name: float(m) for name, m in means.items() if not torch.isnan(m)}
