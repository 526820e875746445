"""The scanned scene as the fitter sees it: an SDF for the penetration and contact terms,
exact triangle queries for the statistics, both in the camera frame of one recording."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from . import assets
from .contact_distance import ContactDistance
from .inside_depth import InsideDepth
from .scene_sdf import (SignedDistanceField, cached_sdf, cached_surface,
                        triangle_signed_distance)


# Surface samples whose faces are searched for a point's nearest triangle in the
# penetration term (the statistics search 6, scene_sdf.triangle_signed_distance).
EXACT_K = 4
RAY_STEP = 0.01  # m between samples along a ray
SURFACE = 0.006  # m: a ray sample this close to the scan has met a surface (> RAY_STEP / 2)
RAY_MARGIN = 0.06  # m before a joint (its own flesh) and after the camera that do not count


class Scene:
    """A static scene mesh (world frame, z up) seen by a camera with pose ``cam2world``;
    ``cache_dir`` keeps its surface samples' grid between runs (:func:`cached_surface`)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cam2world: np.ndarray,
                 sdf: SignedDistanceField, sample_spacing: float = 0.02,
                 cache_dir: Path | None = None) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.cam2world = torch.tensor(cam2world, dtype=torch.float32)
        self.sdf = sdf
        self._camera_sdf = sdf.seen_from(self.cam2world)
        tri = torch.from_numpy(self.vertices[self.faces])  # float64: exact queries
        normals = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self._triangles64 = tri
        self._areas64 = normals.norm(dim=1) / 2
        self._normals64 = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-12)
        self._sample_face, self._samples = cached_surface(self.vertices, self.faces,
                                                          sample_spacing, cache_dir)
        self.contact_distance = ContactDistance(self._camera_sdf, sdf.reader, self.cam2world,
                                                sdf.voxel_size / 2)
        self._inside_depth = InsideDepth(
            self._camera_sdf, self.cam2world, self._samples,
            torch.from_numpy(self._sample_face[self._samples.order]), tri, self._normals64,
            EXACT_K)

    @classmethod
    def load(cls, vertices: np.ndarray, faces: np.ndarray, cam2world: np.ndarray,
             sdf_paths: tuple[Path, Path] | None = None, dim: int = 256) -> "Scene":
        """Use the recording's PROX SDF files when present, else the SDF cache."""
        cache_dir = assets.sdf_cache_dir()
        if sdf_paths is not None and all(p.exists() for p in sdf_paths):
            sdf = SignedDistanceField.load(*sdf_paths)
        else:
            sdf = cached_sdf(vertices, faces, cache_dir, dim=dim)
        return cls(vertices, faces, cam2world, sdf, cache_dir=cache_dir)

    def to_world(self, points: torch.Tensor) -> torch.Tensor:
        return points @ self.cam2world[:3, :3].T + self.cam2world[:3, 3]

    def up_in_camera(self) -> torch.Tensor:
        """World up (+z) expressed in camera coordinates: R^T e_z, the third row of the
        camera-to-world rotation (its third column is the viewing axis in the world)."""
        return self.cam2world[2, :3].clone()

    def signed_distance(self, points_cam: torch.Tensor) -> torch.Tensor:
        """Signed distances from the SDF grid at camera-frame points (..., 3), negative
        inside the scene."""
        return self._camera_sdf(points_cam)

    @torch.no_grad()
    def penetration_depth(self, points_cam: torch.Tensor, exact_band: float
                          ) -> tuple[torch.Tensor, torch.Tensor]:
        """How deep (>= 0) camera-frame points (..., 3) are inside the scene, and the
        depth's gradient in the points (..., 3): from the SDF grid, and, for points the
        grid puts less than ``exact_band`` inside a surface or outside it by less than
        could still be inside, from the nearest triangles themselves, which resolves
        furniture thinner than a voxel (the gradient of such a distance is the unit vector
        from the nearest surface point to the point, signed; :mod:`inside_depth`).

        Farther outside no point can be inside: the grid's corners hold exact distances
        near surfaces, which change by at most the distance moved, so at a point inside
        every corner of its cell reads less than its distance from the point, and the
        trilinear blend of those less than the blend of those distances
        (:func:`trilinear.blend_reach`, under sqrt(3) / 2 of a voxel; a voxel at most).
        Skipping the exact query there leaves two fifths of the points within a voxel
        outside to query (a speed seed's scene stages). The two disagree only where a noisy
        scan edge flips the nearest face's sign (4 of 274,000 readings on seed 0's sofa,
        read 2-6 cm inside): there the grid's reading, outside, stands."""
        depth, slope, left = self._inside_depth(points_cam, (-exact_band, self.sdf.voxel_size))
        left = torch.nonzero(left).flatten()
        if len(left):  # points the sample grid left to the k-d tree
            world = self.to_world(points_cam.reshape(-1, 3)[left]).double()
            exact, closest = self._triangle_distance(world)  # sign * distance (> 0)
            away = (world - closest) * (exact / exact.square())[:, None]  # sign * unit / d
            inside = (exact < 0)[:, None]
            depth[left] = torch.relu(-exact.float())
            slope[left] = -(away.float() @ self.cam2world[:3, :3]) * inside
        return depth.reshape(points_cam.shape[:-1]), slope.reshape(points_cam.shape)

    def _triangle_distance(self, world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return triangle_signed_distance(world, self._samples, self._sample_face,
                                        self._triangles64, self._normals64, k=EXACT_K)

    @torch.no_grad()
    def exact_signed_distance(self, points_cam: torch.Tensor) -> torch.Tensor:
        """Signed distances (N,) at camera-frame points from the nearest triangles
        themselves, which resolves surfaces thinner than a voxel: a 3 cm tabletop is a 3 cm
        slab here, nothing on a 3 cm grid; signed by the area-weighted vote of the nearest
        faces (:func:`triangle_signed_distance`), which noisy edges cannot flip."""
        distance, _ = triangle_signed_distance(self.to_world(points_cam).double(),
                                               self._samples, self._sample_face, self._triangles64,
                                               self._normals64, areas=self._areas64)
        return distance.float()

    @torch.no_grad()
    def first_hits(self, starts: torch.Tensor, directions: torch.Tensor, near: torch.Tensor,
                   far: torch.Tensor) -> torch.Tensor:
        """Per ray (camera-frame ``starts`` and unit ``directions``, (R, 3)), the distance
        along it, between ``near`` and ``far`` (R,), of the first sample (every 1 cm)
        within 6 mm of the scan (:meth:`_on_surface`); inf where there is none."""
        first = torch.full((len(starts),), math.inf)
        if len(starts) == 0:
            return first
        steps = torch.arange(0.0, float(far.max()) + RAY_STEP, RAY_STEP)
        ray, k = torch.nonzero((steps[None] >= near[:, None]) & (steps[None] <= far[:, None]),
                               as_tuple=True)
        met = self._on_surface(starts[ray] + directions[ray] * steps[k, None])
        return first.scatter_reduce_(0, ray[met], steps[k[met]], "amin")

    @torch.no_grad()
    def nearest_hit(self, starts: torch.Tensor, directions: torch.Tensor, far: float,
                    chunk: int = 4) -> float:
        """``first_hits(starts, directions, 0, far).min()``, stepping all rays ``chunk``
        samples at a time and stopping at the first samples that meet the scan: a body
        resting on a surface meets it within a step or two, so a few of its samples need
        exact distances instead of every one near the surface along 50 cm."""
        steps = torch.arange(0.0, far + RAY_STEP, RAY_STEP)
        steps = steps[steps <= far] if len(starts) else steps[:0]
        for first in range(0, len(steps), chunk):
            step = steps[first:first + chunk]
            met = self._on_surface(
                (starts[:, None] + directions[:, None] * step[:, None]).reshape(-1, 3))
            if len(met):
                return float(step[met % len(step)].min())
        return math.inf

    def _on_surface(self, samples: torch.Tensor) -> torch.Tensor:
        """Indices of the camera-frame samples (N, 3) within SURFACE of the scan: the grid
        SDF picks those worth an exact distance."""
        close = torch.nonzero(self.signed_distance(samples).abs()
                              < 2 * self.sdf.voxel_size).flatten()
        return close[self.exact_signed_distance(samples[close]).abs() < SURFACE]

    def visible_scale(self, joints_cam: torch.Tensor, max_scale: float) -> torch.Tensor:
        """Per camera-frame joint (N, 3), the largest scale about the camera centre (up to
        ``max_scale``; inf beyond) at which it is still in front of the scan: the first
        surface its ray meets after RAY_MARGIN, plus RAY_MARGIN (the joint's own flesh)."""
        length = joints_cam.norm(dim=1)
        hits = self.first_hits(torch.zeros_like(joints_cam), joints_cam / length[:, None],
                               torch.full_like(length, RAY_MARGIN),
                               max_scale * length - RAY_MARGIN)
        return (hits + RAY_MARGIN) / length

    def world_normals(self, normals_cam: torch.Tensor) -> torch.Tensor:
        return normals_cam @ self.cam2world[:3, :3].T
