"""Depth input for SMPLify-D / PROX-D: body-mask points from a depth frame.

``recordings/<rec>/Depth/<frame>.png``: 16-bit depth in millimetres x 8 (PROX), registered to
the colour camera; ``BodyIndex/<frame>.png``: Kinect body index, 255 = background. When the
depth resolution differs from the colour one the colour intrinsics are scaled to it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .camera import Camera
from .errors import InputError

DEPTH_SCALE = 1.0 / 8000.0  # PNG value -> metres
COLOR_SIZE = (1920, 1080)


def _read(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            return np.asarray(image)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read image ({exc})") from exc


def load_depth_points(depth_path: Path, mask_path: Path, camera: Camera, flip: bool,
                      max_points: int, seed: int = 0) -> torch.Tensor:
    """Camera-frame points (N, 3) of the depth pixels inside the body mask."""
    depth = _read(depth_path).astype(np.float64) * DEPTH_SCALE
    mask = _read(mask_path)
    if mask.ndim == 3:
        mask = mask[..., 0]
    if depth.ndim != 2 or depth.shape != mask.shape:
        raise InputError(mask_path, f"body mask {mask.shape} does not match depth {depth.shape}")
    if flip:
        depth, mask = depth[:, ::-1], mask[:, ::-1]
    height, width = depth.shape
    sx = width / (camera.width or COLOR_SIZE[0])
    sy = height / (camera.height or COLOR_SIZE[1])
    v, u = np.nonzero((mask != 255) & (depth > 0.1))
    if len(u) > max_points:
        keep = np.random.default_rng(seed).choice(len(u), max_points, replace=False)
        u, v = u[keep], v[keep]
    scaled = Camera(camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy)
    z = torch.tensor(depth[v, u], dtype=torch.float32)
    return scaled.backproject(torch.tensor(u, dtype=torch.float32),
                              torch.tensor(v, dtype=torch.float32), z)
