"""Trilinear reads of a dense grid at points, and their gradient, in one warp kernel.

What ``torch.nn.functional.grid_sample`` computes for a (dim_x, dim_y, dim_z) grid with
``align_corners=True`` and ``padding_mode="border"`` (a point outside the box reads the
border, with no gradient across it), for the scene's signed distance field. torch's CPU
kernel spent 0.15-0.5 ms a call on the 6,400 vertices a scene stage reads, and its backward
as much again: about a ninth of a frame's time, in the scene stages and the scale search.
This kernel reads the eight corners once per point and writes the value and, when asked,
its gradient, which the backward pass only scales. A reader may take its points in another
frame (the camera's): the rigid move to the grid's is folded into the kernel's map from
points to grid coordinates, which saved a (N, 3) x (3, 3) product forward and back (50-75
us each for the scene terms' 6,400 vertices: BLAS is slow at three columns)."""
from __future__ import annotations

import torch
import warp as wp

from .warp_launch import CpuKernel


@wp.func
def read_grid(grid: wp.array3d(dtype=wp.float32), linear: wp.mat33, offset: wp.vec3,
              p: wp.vec3, slopes: int) -> tuple[float, wp.vec3]:
    """The grid's trilinear reading at ``p`` (mapped to grid coordinates by ``linear`` p +
    ``offset``) and, if ``slopes``, its gradient in ``p`` (else zero); NaN at NaN."""
    top = wp.vec3(float(grid.shape[0] - 1), float(grid.shape[1] - 1),
                  float(grid.shape[2] - 1))
    u = linear * p + offset  # grid coordinates
    inside = wp.vec3(1.0, 1.0, 1.0)  # the border clamps a coordinate, and its gradient
    for a in range(3):
        if u[a] != u[a]:  # not a number: no corner to read
            return wp.nan, wp.vec3(0.0, 0.0, 0.0)
        if u[a] <= 0.0:
            u[a] = 0.0
            inside[a] = 0.0
        elif u[a] >= top[a]:
            u[a] = top[a]
            inside[a] = 0.0
    x0 = wp.min(int(wp.floor(u[0])), grid.shape[0] - 2)
    y0 = wp.min(int(wp.floor(u[1])), grid.shape[1] - 2)
    z0 = wp.min(int(wp.floor(u[2])), grid.shape[2] - 2)
    fx = u[0] - float(x0)
    fy = u[1] - float(y0)
    fz = u[2] - float(z0)
    c000 = grid[x0, y0, z0]
    c001 = grid[x0, y0, z0 + 1]
    c010 = grid[x0, y0 + 1, z0]
    c011 = grid[x0, y0 + 1, z0 + 1]
    c100 = grid[x0 + 1, y0, z0]
    c101 = grid[x0 + 1, y0, z0 + 1]
    c110 = grid[x0 + 1, y0 + 1, z0]
    c111 = grid[x0 + 1, y0 + 1, z0 + 1]
    c00 = c000 + (c001 - c000) * fz  # along z, then y, then x
    c01 = c010 + (c011 - c010) * fz
    c10 = c100 + (c101 - c100) * fz
    c11 = c110 + (c111 - c110) * fz
    c0 = c00 + (c01 - c00) * fy
    c1 = c10 + (c11 - c10) * fy
    gradient = wp.vec3(0.0, 0.0, 0.0)
    if slopes != 0:  # the blend's derivatives in the grid's coordinates, then the points'
        dx = c1 - c0
        dy = (c01 - c00) + ((c11 - c10) - (c01 - c00)) * fx
        dz0 = (c001 - c000) + ((c011 - c010) - (c001 - c000)) * fy
        dz1 = (c101 - c100) + ((c111 - c110) - (c101 - c100)) * fy
        dz = dz0 + (dz1 - dz0) * fx
        gradient = wp.transpose(linear) * wp.cw_mul(wp.vec3(dx, dy, dz), inside)
    return c0 + (c1 - c0) * fx, gradient


@wp.func
def blend_reach(grid: wp.array3d(dtype=wp.float32), linear: wp.mat33, offset: wp.vec3,
                p: wp.vec3) -> float:
    """How much more than the distance function itself :func:`read_grid` can read at ``p``
    from a grid of exact distances: the blend's weighted mean distance (m) from ``p`` to
    the eight corners it reads (a 1-Lipschitz function's corner values exceed its value at
    ``p`` by at most their distances); infinite where the border clamps a coordinate."""
    u = linear * p + offset
    spacing = wp.vec3(0.0, 0.0, 0.0)
    for a in range(3):
        if not (u[a] > 0.0 and u[a] < float(grid.shape[a] - 1)):
            return wp.inf
        spacing[a] = 1.0 / wp.length(wp.vec3(linear[a, 0], linear[a, 1], linear[a, 2]))
    f = u - wp.vec3(wp.floor(u[0]), wp.floor(u[1]), wp.floor(u[2]))
    reach = float(0.0)
    for corner in range(8):
        weight = float(1.0)
        gap = wp.vec3(0.0, 0.0, 0.0)
        for a in range(3):
            if (corner >> a) & 1 == 1:
                weight *= f[a]
                gap[a] = (1.0 - f[a]) * spacing[a]
            else:
                weight *= 1.0 - f[a]
                gap[a] = f[a] * spacing[a]
        reach += weight * wp.length(gap)
    return reach


@wp.kernel
def _read(grid: wp.array3d(dtype=wp.float32), points: wp.array(dtype=wp.vec3),
          linear: wp.mat33, offset: wp.vec3, slopes: int,
          values: wp.array(dtype=wp.float32), gradient: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    value, slope = read_grid(grid, linear, offset, points[i], slopes)
    values[i] = value
    if slopes != 0:
        gradient[i] = slope


_READ = CpuKernel(_read, (wp.float32, wp.vec3, None, None, None, wp.float32, wp.vec3))


class Trilinear:
    """Reads of ``grid`` (dim_x, dim_y, dim_z) float32, whose corner samples span the box
    ``bmin``..``bmax`` (3,), at points (..., 3) in the grid's frame or, given the rigid
    transform ``frame`` (4, 4) from theirs to the grid's, in their own; differentiable in
    the points."""

    def __init__(self, grid: torch.Tensor, bmin: torch.Tensor, bmax: torch.Tensor,
                 frame: torch.Tensor | None = None) -> None:
        self.grid = grid.detach().float().contiguous()
        top = torch.tensor(self.grid.shape, dtype=torch.float64) - 1
        scale = top / (bmax.double() - bmin.double())
        frame = torch.eye(4, dtype=torch.float64) if frame is None else frame.double()
        linear = scale[:, None] * frame[:3, :3]  # u = scale (R p + t - bmin)
        offset = scale * (frame[:3, 3] - bmin.double())
        self.linear = wp.mat33(*linear.flatten().tolist())
        self.offset = wp.vec3(*offset.tolist())

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return _Read.apply(points, self)

    def read(self, points: torch.Tensor, slopes: bool = True
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """Float32 reads (...) at ``points`` (..., 3) and, with ``slopes``, their
        gradients in the points (..., 3) (else an empty tensor), without autograd."""
        flat = points.detach().reshape(-1, 3).float().contiguous()
        values = torch.empty(len(flat))
        gradient = torch.empty((len(flat) if slopes else 0, 3))
        _READ(len(flat), self.grid, flat, self.linear, self.offset, int(slopes), values,
              gradient)
        return (values.reshape(points.shape[:-1]),
                gradient.reshape(*points.shape) if slopes else gradient)


class _Read(torch.autograd.Function):
    @staticmethod
    def forward(ctx, points: torch.Tensor, reader: Trilinear) -> torch.Tensor:
        values, gradient = reader.read(points, slopes=ctx.needs_input_grad[0])
        ctx.save_for_backward(gradient)
        ctx.dtype = points.dtype
        return values.to(points.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor | None, None]:
        (gradient,) = ctx.saved_tensors
        return (grad[..., None].float() * gradient).to(ctx.dtype), None
