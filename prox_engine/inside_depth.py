"""How deep camera-frame points are inside the scene, and the depth's gradient, in one warp
kernel (:meth:`Scene.penetration_depth`): the SDF grid's reading, replaced near surfaces by
the exact distance to the nearest of the faces of each point's nearest surface samples.

The penetration term asks this of 6,400 vertices some fifty times a frame, 900 of them
near a surface. As a grid read, then the near points' world coordinates, sample query,
nearest faces, distances and writes back, it was a dozen launches and twenty torch and
numpy operations: 1.4 ms a call, a third of it between the kernels. A point the sample
grid cannot answer alone (far from surfaces, or outside the grid) is flagged and left to
the caller, which answers it with the k-d tree."""
from __future__ import annotations

import torch
import warp as wp

from .nearest_face import FacesK, nearest_face
from .sample_grid import MAX_K, RINGS, SampleGrid, k_nearest
from .trilinear import Trilinear, blend_reach, read_grid
from .warp_launch import CpuKernel, rigid


@wp.kernel
def _inside(points: wp.array(dtype=wp.vec3), grid: wp.array3d(dtype=wp.float32),
            linear: wp.mat33, offset: wp.vec3, rotation: wp.mat33, shift: wp.vec3,
            low: float, high: float, samples: wp.array(dtype=wp.vec3d),
            starts: wp.array(dtype=wp.int32), origin: wp.vec3d, cell: wp.float64,
            dims: wp.vec3i, k: int, rings: int, slot_face: wp.array(dtype=wp.int64),
            corners: wp.array2d(dtype=wp.vec3d), normals: wp.array(dtype=wp.vec3d),
            areas: wp.array(dtype=wp.float64), depth: wp.array(dtype=wp.float32),
            slope: wp.array(dtype=wp.vec3), left: wp.array(dtype=wp.int32)):
    i = wp.tid()
    p = points[i]
    value, gradient = read_grid(grid, linear, offset, p, 0)
    left[i] = 0
    sure = int(0)
    near = value < 0.0
    if value >= 0.0 and value < high:  # the blend's reach only where it can decide
        near = value < blend_reach(grid, linear, offset, p)
    if value > low and near:
        world = wp.vec3d(rotation * p + shift)
        if wp.isfinite(world):
            index, best, sure = k_nearest(world, samples, starts, origin, cell, dims, k, rings)
            if sure != 0:
                faces = FacesK()
                for j in range(k):
                    faces[j] = slot_face[index[j]]
                q, side = nearest_face(world, faces, k, corners, normals, areas, 0)
                d = world - q
                exact = wp.sqrt(wp.dot(d, d) + wp.float64(1e-14)) * side
                value = wp.float32(exact)
                gradient = wp.transpose(rotation) * wp.vec3(d / exact)
        if sure == 0:
            left[i] = 1
    if value < 0.0 and sure == 0:  # the grid's own reading stands: its gradient too
        value, gradient = read_grid(grid, linear, offset, p, 1)
    depth[i] = wp.where(value < 0.0, -value, value * 0.0)  # NaN stays NaN
    slope[i] = wp.where(value < 0.0, -gradient, wp.vec3(0.0, 0.0, 0.0))


_INSIDE = CpuKernel(_inside, (wp.vec3, wp.float32, *[None] * 6, wp.vec3d, wp.int32,
                              *[None] * 5, wp.int64, wp.vec3d, wp.vec3d, wp.float64,
                              wp.float32, wp.vec3, wp.int32))


class InsideDepth:
    """How deep camera-frame points are inside a scene: its SDF ``reader`` (in the points'
    frame), replaced near surfaces by the distance to the nearest point of the nearest of
    the faces (``triangles`` (F, 3, 3) float64 in the world frame, ``cam2world`` (4, 4)
    from the points', with unit ``normals``) of the point's ``k`` nearest surface samples
    in ``grid`` (``slot_face`` (S,): each grid slot's face), signed by that face's side."""

    def __init__(self, reader: Trilinear, cam2world: torch.Tensor, grid: SampleGrid,
                 slot_face: torch.Tensor, triangles: torch.Tensor, normals: torch.Tensor,
                 k: int) -> None:
        if not 0 < k <= MAX_K:
            raise ValueError(f"k = {k}: 1 to {MAX_K} nearest samples")
        self._scene = (reader.grid, reader.linear, reader.offset, *rigid(cam2world))
        self._exact = (grid.samples, grid.starts, wp.vec3d(*grid.origin),
                       wp.float64(grid.cell), wp.vec3i(*grid.dims.tolist()), k, RINGS,
                       slot_face.contiguous(), triangles.contiguous(), normals.contiguous(),
                       normals[:0, 0])  # no areas: no vote

    def __call__(self, points: torch.Tensor, band: tuple[float, float]
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per point (N, 3): its depth (>= 0, float32) inside the scene, the depth's
        gradient in the point (N, 3), and whether it is left undone (N,) bool: exact where
        the grid reads above ``band``'s low and inside, or outside by less than both its
        high and the blend of the grid corners' distances (:func:`trilinear.blend_reach`:
        farther outside nothing can be inside), except at points the sample grid cannot
        answer alone (far from every sample, or outside the grid), whose depth is the
        SDF's."""
        flat = points.detach().reshape(-1, 3).float().contiguous()
        n = len(flat)
        depth, slope = torch.empty(n), torch.empty(n, 3)
        left = torch.empty(n, dtype=torch.int32)
        _INSIDE(n, flat, *self._scene, float(band[0]), float(band[1]), *self._exact, depth,
                slope, left)
        return depth, slope, left.bool()
