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


@wp.func
def _world_normal(world: wp.vec3, grid: wp.array3d(dtype=wp.float32), world_linear: wp.mat33,
                  world_offset: wp.vec3, h: float) -> wp.vec3:
    """The SDF's outward unit normal at ``world`` (central differences over ``h``)."""
    probes = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        step = wp.vec3(0.0, 0.0, 0.0)
        step[a] = h
        ahead, unused = read_grid(grid, world_linear, world_offset, world + step, 0)
        behind, unused2 = read_grid(grid, world_linear, world_offset, world - step, 0)
        probes[a] = ahead - behind
    return probes / wp.max(wp.length(probes), 1e-9)


@wp.func
def _faces(p: wp.vec3, normal: wp.vec3, grid: wp.array3d(dtype=wp.float32),
           world_linear: wp.mat33, world_offset: wp.vec3, rotation: wp.mat33, shift: wp.vec3,
           h: float, min_facing: float) -> int:
    """1 if the outward body ``normal`` at camera-frame ``p`` faces the surface: its cosine
    with the opposite of the SDF's normal in the world above ``min_facing``, else 0."""
    outward = _world_normal(rotation * p + shift, grid, world_linear, world_offset, h)
    return wp.where(-wp.dot(rotation * normal, outward) > min_facing, 1, 0)


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
        qualifies = _faces(p, normals[i], grid, world_linear, world_offset, rotation, shift,
                           h, min_facing)
    valid[i] = qualifies


@wp.kernel
def _nearest_contact(points: wp.array2d(dtype=wp.vec3), normals: wp.array2d(dtype=wp.vec3),
                     starts: wp.array(dtype=wp.int32), grid: wp.array3d(dtype=wp.float32),
                     linear: wp.mat33, offset: wp.vec3, world_linear: wp.mat33,
                     world_offset: wp.vec3, rotation: wp.mat33, shift: wp.vec3, h: float,
                     max_distance: float, min_facing: float,
                     nearest: wp.array2d(dtype=wp.float32)):
    row, part = wp.tid()
    best = max_distance
    found = int(0)
    for i in range(starts[part], starts[part + 1]):
        p = points[row, i]
        signed, unused = read_grid(grid, linear, offset, p, 0)
        d = wp.abs(signed)
        if d < best:  # only a nearer point can change the answer: test its facing
            if _faces(p, normals[row, i], grid, world_linear, world_offset, rotation, shift,
                      h, min_facing) != 0:
                best = d
                found = 1
    nearest[row, part] = wp.where(found != 0, best, wp.inf)


@wp.kernel
def _upward(world: wp.array(dtype=wp.vec3), gaps: wp.array(dtype=wp.float32),
            low: wp.array(dtype=wp.int32), starts: wp.array(dtype=wp.int32),
            grid: wp.array3d(dtype=wp.float32), world_linear: wp.mat33, world_offset: wp.vec3,
            h: float, min_up: float, nearest: wp.array2d(dtype=wp.float32)):
    row = wp.tid()
    best = float(wp.inf)
    best_low = float(wp.inf)
    for i in range(starts[row], starts[row + 1]):
        d = gaps[i]
        if d < best or (low[i] != 0 and d < best_low):  # else its normal cannot matter
            if _world_normal(world[i], grid, world_linear, world_offset, h)[2] > min_up:
                best = wp.min(best, d)
                if low[i] != 0:
                    best_low = wp.min(best_low, d)
    nearest[row, 0] = best_low
    nearest[row, 1] = best


_CONTACT = CpuKernel(_contact, (wp.vec3, wp.vec3, wp.float32, wp.float32, *[None] * 9,
                                wp.float32, wp.int32, wp.vec3))
_UPWARD = CpuKernel(_upward, (wp.vec3, wp.float32, wp.int32, wp.int32, wp.float32,
                              *[None] * 4, wp.float32))
_NEAREST = CpuKernel(_nearest_contact, (wp.vec3, wp.vec3, wp.int32, wp.float32,
                                         *[None] * 9, wp.float32))


class ContactDistance:
    """Distances to contact in a scene whose SDF ``world`` reads world points and
    ``camera`` reads camera-frame points (``cam2world`` (4, 4) from theirs to the world's),
    with normals by central differences over ``h`` (m)."""

    def __init__(self, camera: Trilinear, world: Trilinear, cam2world: torch.Tensor,
                 h: float) -> None:
        self._scene = (camera.grid, camera.linear, camera.offset, world.linear, world.offset,
                       *rigid(cam2world), float(h))
        self._world = (camera.grid, world.linear, world.offset, float(h))

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

    @torch.no_grad()
    def nearest(self, points: torch.Tensor, normals: torch.Tensor, sizes: list[int],
                max_distance: float, min_facing: float) -> torch.Tensor:
        """Per row of camera-frame points (R, N, 3) with outward body ``normals`` (R, N, 3),
        split into consecutive groups of ``sizes`` points (summing to N), the distance to
        contact (|SDF|) of each group's nearest point that qualifies for it (as in
        :meth:`__call__`), inf where none does: (R, len(sizes)). A point's facing test
        runs only when it is nearer than every qualifying point before it in its group,
        not at every point within ``max_distance`` (two fifths of a body's contact
        vertices, each test six reads against the distance's one)."""
        rows = len(points)
        found = torch.empty(rows, len(sizes))
        _NEAREST((rows, len(sizes)), points.float().contiguous(),
                 normals.float().contiguous(), _starts(sizes), *self._scene, float(max_distance),
                 float(min_facing), found)
        return found

    @torch.no_grad()
    def nearest_upward(self, world: torch.Tensor, gaps: torch.Tensor, low: torch.Tensor,
                       sizes: list[int], min_up: float) -> torch.Tensor:
        """Per group of world points (M, 3) (consecutive groups of ``sizes`` points, summing
        to M) at ``gaps`` (M,) from the scene, the smallest gap of a point where the SDF's
        normal points up (world z above ``min_up``), among the ``low`` (M,) bool points and
        among all: (len(sizes), 2), inf where none. A point's normal is read only when its
        gap is under the smallest found before it."""
        found = torch.empty(len(sizes), 2)
        _UPWARD(len(sizes), world.float().contiguous(), gaps.float().contiguous(),
                low.to(torch.int32).contiguous(), _starts(sizes), *self._world,
                float(min_up), found)
        return found


def _starts(sizes: list[int]) -> torch.Tensor:
    """(len(sizes) + 1,) int32: where each of consecutive groups of ``sizes`` begins, and
    the end."""
    return torch.tensor([0, *sizes], dtype=torch.int32).cumsum(0, dtype=torch.int32)
