"""Pinhole camera with optional OpenCV radial-tangential distortion (OpenCV axes)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class Camera:
    """Intrinsics of the colour camera; points are in camera coordinates (x right, y down,
    z forward)."""

    fx: float
    fy: float
    cx: float
    cy: float
    k: list[float] = field(default_factory=list)  # k1, k2, p1, p2, k3 (any prefix)
    width: int | None = None
    height: int | None = None

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates (..., 2) of camera-space points (..., 3)."""
        z = points[..., 2:3].clamp_min(1e-3)
        xy = points[..., :2] / z
        if any(self.k):
            xy = self._distort(xy)
        return torch.stack([xy[..., 0] * self.fx + self.cx, xy[..., 1] * self.fy + self.cy], -1)

    def backproject(self, u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Camera-space points for pixels (u, v) at metric depth (distortion ignored)."""
        return torch.stack([(u - self.cx) / self.fx * depth, (v - self.cy) / self.fy * depth,
                            depth], -1)

    def rays(self, pixels: torch.Tensor) -> torch.Tensor:
        """Unit camera-space rays (N, 3) through ``pixels`` (N, 2) (distortion ignored)."""
        ray = self.backproject(pixels[:, 0], pixels[:, 1], torch.ones(len(pixels)))
        return ray / ray.norm(dim=-1, keepdim=True)

    def image_direction(self, pixels: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
        """Unit image directions (..., 2) in which a point seen at ``pixels`` (..., 2) moves
        as it moves along the camera-space ``direction`` (3,), whatever its depth
        (distortion ignored)."""
        x, y, _ = self.backproject(pixels[..., 0], pixels[..., 1],
                                   torch.ones_like(pixels[..., 0])).unbind(-1)
        moved = torch.stack([self.fx * (direction[0] - x * direction[2]),
                             self.fy * (direction[1] - y * direction[2])], -1)
        return moved / moved.norm(dim=-1, keepdim=True).clamp_min(1e-9)

    def in_image(self, pixels: torch.Tensor) -> torch.Tensor:
        """(...,) bool: whether ``pixels`` (..., 2) lie in the image (without its size in
        the calibration, twice the principal point)."""
        u, v = pixels.unbind(-1)
        return ((u >= 0) & (u < (self.width or 2 * self.cx))
                & (v >= 0) & (v < (self.height or 2 * self.cy)))

    def _distort(self, xy: torch.Tensor) -> torch.Tensor:
        k = list(self.k) + [0.0] * (5 - len(self.k))
        k1, k2, p1, p2, k3 = k[:5]
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return torch.stack([xd, yd], -1)


@dataclass
class DepthCamera:
    """A depth (IR) camera beside the colour one: intrinsics (3, 3), OpenCV distortion, and
    the rigid transform (4, 4) from its frame to the colour camera's."""

    matrix: np.ndarray
    distortion: np.ndarray
    to_colour: np.ndarray
