"""Distances to contact of camera-frame points and which of them qualify for it, with the
distance's gradient, in one warp kernel (:func:`losses.contact_distances`).

A contact evaluation reads the SDF at each contact vertex, and at those near a surface
the SDF's normal by central differences (six more reads), to test whether the body's
normal there faces the surface. In torch that was some thirty operations and their
autograd nodes, 0.9 ms of a contact evaluation; here one launch reads, tests and writes
the distance's gradient, which the term only scales."""
from __future__ import annotations

import torch
import warp as wp

from .trilinear import Trilinear, read_grid
from .warp_launch import CpuKernel, rigid


@wp.kernel
def _contact(points: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3),
             sink: wp.array(dtype=wp.float32), grid: wp.array3d(dtype=wp.float32),
             linear: wp.mat33, offset: wp.vec3, world_linear: wp.mat33, world_offset: wp.vec3,
             rotation: wp.mat33, shift: wp.vec3, h: float, max_distance: float,
             min_facing: float, dist: wp.array(dtype=wp.float32),
             valid: wp.array(dtype=wp.int32), slope: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    p = points[i]
    signed, gradient = read_grid(grid, linear, offset, p, 1)
    if sink.shape[0] > 0:
        signed += sink[i % sink.shape[0]]
    d = wp.abs(signed)
    dist[i] = d
    slope[i] = wp.where(signed > 0.0, gradient,
                        wp.where(signed < 0.0, -gradient, wp.vec3(0.0, 0.0, 0.0)))
    qualifies = int(0)
    if d < max_distance:  # the facing test, against the SDF's normal in the world
        world = rotation * p + shift
        probes = wp.vec3(0.0, 0.0, 0.0)
        for a in range(3):
            step = wp.vec3(0.0, 0.0, 0.0)
            step[a] = h
            ahead, unused = read_grid(grid, world_linear, world_offset, world + step, 0)
            behind, unused2 = read_grid(grid, world_linear, world_offset, world - step, 0)
            probes[a] = ahead - behind
        outward = probes / wp.max(wp.length(probes), 1e-9)
        if -wp.dot(rotation * normals[i], outward) > min_facing:
            qualifies = 1
    valid[i] = qualifies


_CONTACT = CpuKernel(_contact, (wp.vec3, wp.vec3, wp.float32, wp.float32, *[None] * 9,
                                wp.float32, wp.int32, wp.vec3))


class ContactDistance:
    """Distances to contact in a scene whose SDF ``world`` reads world points and
    ``camera`` reads camera-frame points (``cam2world`` (4, 4) from theirs to the world's),
    with normals by central differences over ``h`` (m)."""

    def __init__(self, camera: Trilinear, world: Trilinear, cam2world: torch.Tensor,
                 h: float) -> None:
        self._scene = (camera.grid, camera.linear, camera.offset, world.linear, world.offset,
                       *rigid(cam2world), float(h))

    @torch.no_grad()
    def __call__(self, points: torch.Tensor, normals: torch.Tensor, max_distance: float,
                 min_facing: float, sink: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """For camera-frame points (..., N, 3) with outward body ``normals`` (..., N, 3):
        the distance to contact |SDF + ``sink``| (..., N) (``sink`` (N,) m, or none), which
        points qualify (..., N) bool (nearer than ``max_distance``, and the body normal's
        cosine with the opposite of the SDF's normal above ``min_facing``), and the
        distance's gradient in the points (..., N, 3)."""
        flat = points.reshape(-1, 3).float().contiguous()
        n = len(flat)
        dist, valid, slope = torch.empty(n), torch.empty(n, dtype=torch.int32), torch.empty(n, 3)
        sink = flat.new_zeros(0) if sink is None else sink.float().contiguous()
        _CONTACT(n, flat, normals.reshape(-1, 3).float().contiguous(), sink, *self._scene,
                 float(max_distance), float(min_facing), dist, valid, slope)
        shape = points.shape[:-1]
        return dist.view(shape), valid.bool().view(shape), slope.view(points.shape)
