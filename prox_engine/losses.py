"""The terms of the PROX objective, each a function returning a (B,) tensor."""
from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
import torch

from .body.base import BodyModel, BodyOutput
from .geometry import grid_subsample, vertex_normals
from .keypoints import BODY, MID_HIP
from .scene import Scene
from .with_gradient import with_gradient

Array = TypeVar("Array", torch.Tensor, np.ndarray)


def gmof(squared: torch.Tensor, rho: float) -> torch.Tensor:
    """Geman-McClure of a squared residual, scaled so that it is ~squared near zero."""
    return rho ** 2 * squared / (squared + rho ** 2)


def penetration_vertices(body: BodyModel, spacing: float, rest: torch.Tensor | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The scene vertices (indices) that the penetration term reads, and how many scene
    vertices each stands for: one per cell of a grid of ``spacing`` (m) over the standing
    mean body (``rest`` (V, 3), posed here if not given), counted for the cell's vertices;
    every one, once each, at 0. anny's face, hands and feet hold two thirds of its
    vertices a few millimetres apart, its trunk and limbs a centimetre or more."""
    ids = torch.nonzero(body.scene_vertices).flatten()
    if spacing <= 0:
        return ids, torch.ones(len(ids))
    if rest is None:
        with torch.no_grad():
            rest = body(body.init_params(1)).vertices[0]
    kept, counts = grid_subsample(rest[ids], spacing)
    return ids[kept], counts.float()


def penetration_energy(points: torch.Tensor, scene: Scene,
                       tolerance: float | torch.Tensor = 0.0,
                       weights: torch.Tensor | None = None) -> torch.Tensor:
    """Sum over points (B, N, 3) more than ``tolerance`` ((N,) or one for all) inside the
    scene, each counted ``weights`` (N,) times (once by default), of d^2 (the paper's
    ||d n||^2) plus |d| (so that shallow penetrations still get a push), d being the depth
    beyond the tolerance: exact (from the triangles) within two voxels of a surface, where
    furniture thinner than a voxel would otherwise be missed, else from the grid. Worked
    out with its gradient, without autograd (:func:`with_gradient`)."""
    return with_gradient(points, *penetration_value_and_slope(points, scene, tolerance,
                                                              weights))


def penetration_value_and_slope(points: torch.Tensor, scene: Scene,
                                tolerance: float | torch.Tensor = 0.0,
                                weights: torch.Tensor | None = None
                                ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`penetration_energy` (B,) and its gradient in the points (B, N, 3)."""
    depth, slope = scene.penetration_depth(points, exact_band=2 * scene.sdf.voxel_size)
    depth = torch.relu(depth - tolerance)
    energy = depth ** 2 + depth
    push = 2 * depth + (depth > 0)  # d energy / d depth
    if weights is not None:
        energy, push = energy * weights, push * weights
    return energy.sum(-1), push[..., None] * slope


# The contact parts of flesh a body rests on (a seated body's buttocks and thighs, a lying
# one's back): they and the cushions under them give, so that a body resting on them lies a
# little inside the scanned surface there (FitConfig.soft_sink), its feet and hands on it.
SOFT_PARTS = ("back", "gluteus", "thighs")
# The vertex parts a misregistered floor may hold inside it (FitConfig.foot_tolerance).
FEET_PARTS = ("left_foot", "right_foot")


def part_vertices(contact_parts: dict[str, torch.Tensor], parts: tuple[str, ...],
                  count: int) -> torch.Tensor:
    """(``count``,) bool: the vertices of those of ``parts`` the body has among its
    ``contact_parts`` (part -> vertex indices)."""
    mask = torch.zeros(count, dtype=torch.bool)
    for part in parts:
        if part in contact_parts:
            mask[contact_parts[part]] = True
    return mask


def contact_distances(points: torch.Tensor, normals: torch.Tensor, scene: Scene,
                      max_angle_deg: float, max_distance: float,
                      sink: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Distance to contact of points (..., N, 3) with outward body normals, which of them
    qualify for contact, and the distance's gradient in the points (..., N, 3), without
    autograd: within ``max_distance`` of it with the normal facing the surface (within
    ``max_angle_deg`` of the opposite of the SDF gradient, by central differences over
    half a voxel). A point touches on the scene's surface (|SDF|), or ``sink`` (N,) metres
    inside it (|SDF + sink|: flesh and cushions that give). The SDF makes this one grid
    lookup per point instead of a nearest-triangle search, exact on planes and close to it
    elsewhere (:class:`contact_distance.ContactDistance`)."""
    return scene.contact_distance(points, normals, max_distance,
                                  math.cos(math.radians(max_angle_deg)), sink)


def nearest_contacts(points: torch.Tensor, normals: torch.Tensor, sizes: list[int],
                     scene: Scene, max_angle_deg: float, max_distance: float) -> torch.Tensor:
    """Per row of points (R, N, 3) with outward body normals, split into consecutive parts
    of ``sizes`` points, the distance to contact of each part's nearest point that
    qualifies for it (:func:`contact_distances`, without ``sink``), inf where none does:
    (R, len(sizes))."""
    return scene.contact_distance.nearest(points, normals, sizes, max_distance,
                                          math.cos(math.radians(max_angle_deg)))


def contact_energy(points: torch.Tensor, normals: torch.Tensor, scene: Scene, rho: float,
                   max_angle_deg: float, max_distance: float,
                   sink: torch.Tensor | None = None) -> torch.Tensor:
    """Robust distance to contact of the points (B, N, 3) that qualify for it
    (:func:`contact_distances`, touching ``sink`` deep), averaged over those points as in
    PROX; 0 when none qualifies. Worked out with its gradient (:func:`with_gradient`)."""
    return with_gradient(points, *contact_value_and_slope(points, normals, scene, rho,
                                                          max_angle_deg, max_distance, sink))


def contact_value_and_slope(points: torch.Tensor, normals: torch.Tensor, scene: Scene,
                            rho: float, max_angle_deg: float, max_distance: float,
                            sink: torch.Tensor | None = None
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`contact_energy` (B,) and its gradient in the points (B, N, 3)."""
    dist, valid, slope = contact_distances(points, normals, scene, max_angle_deg, max_distance,
                                           sink)
    count = valid.sum(1, keepdim=True).clamp_min(1)
    squared = dist ** 2
    energy = (gmof(squared, rho) / rho ** 2 * valid).sum(1) / count[:, 0]
    push = valid * (2 * dist / (squared + rho ** 2) ** 2 * rho ** 2) / count  # d / d dist
    return energy, push[..., None] * slope


def self_penetration(out: BodyOutput, body: BodyModel) -> torch.Tensor:
    """Squared overlap of collision spheres that must not meet (arms/torso, leg/leg)."""
    if out.spheres is None or len(body.collision_pairs) == 0:
        return out.keypoints.new_zeros(out.keypoints.shape[0])
    a = out.spheres[:, body.collision_pairs[:, 0]]
    b = out.spheres[:, body.collision_pairs[:, 1]]
    overlap = torch.relu(a[..., 3] + b[..., 3] - (a[..., :3] - b[..., :3]).norm(dim=-1))
    return (overlap ** 2).sum(1)


def facing_camera(vertices: torch.Tensor, body: BodyModel) -> torch.Tensor:
    """(B, V) which body vertices (camera frame) face the camera: what a depth camera can
    see of the body, eyes and tongue left out."""
    normals = vertex_normals(vertices, body.faces)
    return ((normals * vertices).sum(-1) < 0) & body.scene_vertices


def depth_data(out: BodyOutput, body: BodyModel, points: list[torch.Tensor | None],
               rho: float) -> torch.Tensor:
    """Robust distance from each body-mask depth point to the nearest camera-facing body
    vertex (SMPLify-D); points per batch element, in camera coordinates."""
    seen = facing_camera(out.vertices, body)
    terms = []
    for b, cloud in enumerate(points):
        if cloud is None or len(cloud) == 0:
            terms.append(out.vertices.new_zeros(()))
            continue
        visible = out.vertices[b, seen[b]]
        with torch.no_grad():  # which vertex is nearest; the distance keeps its gradient
            nearest = torch.cdist(cloud, visible).argmin(1)
        squared = ((cloud - visible[nearest]) ** 2).sum(-1)
        terms.append(gmof(squared, rho).mean())
    return torch.stack(terms)


def temporal(out: BodyOutput, previous: torch.Tensor | None,
             about_root: bool = False) -> torch.Tensor:
    """Squared 3D keypoint motion (m^2) to the previous frame's fit (sequence mode); with
    ``about_root``, of the keypoints about the mid-hip: the posture's change, not the
    body's travel."""
    if previous is None:
        return out.keypoints.new_zeros(out.keypoints.shape[0])
    return (_motion(out.keypoints, previous, about_root) ** 2).sum((1, 2))


def temporal_value_and_slope(keypoints: torch.Tensor, previous: torch.Tensor,
                             about_root: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`temporal` of posed ``keypoints`` (B, K, 3) and its gradient in them (B, K, 3),
    without autograd (for :class:`keypoint_objective.KeypointObjective`), in numpy: a
    keypoint stage evaluates it a hundred times a frame, and in torch it cost 24 us."""
    motion = _motion(keypoints.detach().numpy(), previous.detach().numpy(), about_root)
    slope = np.zeros(keypoints.shape, np.float32)
    slope[:, BODY] = 2 * motion
    if about_root:  # the mid-hip's own motion was taken from every keypoint's
        slope[:, MID_HIP] -= 2 * motion.sum(1)
    return torch.from_numpy((motion ** 2).sum((1, 2))), torch.from_numpy(slope)


def _motion(keypoints: Array, previous: Array, about_root: bool) -> Array:
    """(B, 25, 3) the body keypoints' motion from ``previous``, about the mid-hip's with
    ``about_root``."""
    motion = keypoints[:, BODY] - previous[:, BODY]
    if about_root:
        motion = motion - motion[:, MID_HIP:MID_HIP + 1]
    return motion
