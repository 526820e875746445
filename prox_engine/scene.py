"""The scanned scene as the fitter sees it: an SDF for penetration, exact surface queries
for contact, both in the camera frame of one recording."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from . import assets
from .geometry import closest_point_on_triangles
from .scene_sdf import SignedDistanceField, cached_sdf, surface_samples


class Scene:
    """A static scene mesh (world frame, z up) seen by a camera with pose ``cam2world``."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cam2world: np.ndarray,
                 sdf: SignedDistanceField, sample_spacing: float = 0.02) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.cam2world = torch.tensor(cam2world, dtype=torch.float32)
        self.sdf = sdf
        tri = torch.tensor(self.vertices[self.faces], dtype=torch.float32)
        normals = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.triangles = tri
        self.face_normals = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-12)
        samples, self._sample_face = surface_samples(self.vertices, self.faces, sample_spacing)
        self._tree = cKDTree(samples)

    @classmethod
    def load(cls, vertices: np.ndarray, faces: np.ndarray, cam2world: np.ndarray,
             sdf_paths: tuple[Path, Path] | None = None, dim: int = 256) -> "Scene":
        """Use the recording's PROX SDF files when present, else the SDF cache."""
        if sdf_paths is not None and all(p.exists() for p in sdf_paths):
            sdf = SignedDistanceField.load(*sdf_paths)
        else:
            sdf = cached_sdf(vertices, faces, assets.sdf_cache_dir(), dim=dim)
        return cls(vertices, faces, cam2world, sdf)

    def to_world(self, points: torch.Tensor) -> torch.Tensor:
        return points @ self.cam2world[:3, :3].T + self.cam2world[:3, 3]

    def up_in_camera(self) -> torch.Tensor:
        """World up (+z) expressed in camera coordinates: R^T e_z, the third row of the
        camera-to-world rotation (its third column is the viewing axis in the world)."""
        return self.cam2world[2, :3].clone()

    def signed_distance(self, points_cam: torch.Tensor) -> torch.Tensor:
        """SDF values at camera-frame points (..., 3); negative inside the scene."""
        return self.sdf(self.to_world(points_cam))

    def sdf_normals(self, points_cam: torch.Tensor) -> torch.Tensor:
        """Outward scene normals (world frame, no gradient) at camera-frame points."""
        return self.sdf.normals(self.to_world(points_cam))

    def closest_surface(self, points_cam: torch.Tensor, k: int = 6
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """Distance (N,) to the nearest scene surface point and that face's normal (N, 3),
        the normal in world coordinates. Differentiable in the points; the candidate faces
        (those of the k nearest surface samples) are found without gradient."""
        world = self.to_world(points_cam)
        # A line-search probe may produce non-finite points: query somewhere harmless; the
        # non-finite loss then makes the optimiser reject the step.
        query = np.nan_to_num(world.detach().numpy(), nan=0.0, posinf=1e6, neginf=-1e6)
        _, nearest = self._tree.query(query, k=k)
        cand = torch.from_numpy(self._sample_face[nearest])
        tri = self.triangles[cand]
        p = world[:, None].expand(-1, k, -1)
        closest = closest_point_on_triangles(p, tri[:, :, 0], tri[:, :, 1], tri[:, :, 2])
        dist = (p - closest).norm(dim=-1)
        best = dist.argmin(dim=1, keepdim=True)
        face = cand.gather(1, best)[:, 0]
        return dist.gather(1, best)[:, 0], self.face_normals[face]

    def world_normals(self, normals_cam: torch.Tensor) -> torch.Tensor:
        return normals_cam @ self.cam2world[:3, :3].T
