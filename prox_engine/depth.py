"""Depth input: body-mask points for SMPLify-D / PROX-D, scene points to re-register the scan.

``recordings/<rec>/Depth/<frame>.png``: 16-bit depth in millimetres x 8 (PROX);
``BodyIndex/<frame>.png``: Kinect body index, 255 = background. Real PROX depth comes from
the Kinect's 512x424 depth (IR) camera, calibrated in ``calibration/IR.json`` (or
``depth.json``): its pixels are undistorted with that camera's intrinsics and distortion,
scaled by their depth and moved into the colour camera's frame through both cameras'
``view_mtx``, as PROX does. Without an IR calibration the depth is taken as registered to
the colour camera, whose intrinsics are scaled to the depth resolution.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from PIL import Image

from .camera import Camera, DepthCamera
from .errors import InputError

DEPTH_SCALE = 1.0 / 8000.0  # PNG value -> metres
COLOR_SIZE = (1920, 1080)
SILHOUETTE_PX = 3  # the body mask grows by this much before scene pixels are taken


def _read(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            return np.asarray(image)
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot read image ({exc})") from exc


def load_depth_points(depth_path: Path, mask_path: Path, camera: Camera, flip: bool,
                      max_points: int, seed: int = 0,
                      depth_camera: DepthCamera | None = None, body: bool = True
                      ) -> torch.Tensor:
    """Colour-camera-frame points (N, 3) of the depth pixels inside the body mask (or, with
    ``body=False``, of the scene: off the mask grown by SILHOUETTE_PX, where depth pixels
    mix body and background), through ``depth_camera`` when given, else with the depth
    registered to ``camera``."""
    depth = _read(depth_path).astype(np.float64) * DEPTH_SCALE
    mask = _read(mask_path)
    if mask.ndim == 3:
        mask = mask[..., 0]
    if depth.ndim != 2 or depth.shape != mask.shape:
        raise InputError(mask_path, f"body mask {mask.shape} does not match depth {depth.shape}")
    if flip:
        depth, mask = depth[:, ::-1], mask[:, ::-1]
    region = mask != 255
    if not body:
        kernel = np.ones((2 * SILHOUETTE_PX + 1,) * 2, np.uint8)
        region = cv2.dilate(region.astype(np.uint8), kernel) == 0
    v, u = np.nonzero(region & (depth > 0.1))
    if len(u) > max_points:
        keep = np.random.default_rng(seed).choice(len(u), max_points, replace=False)
        u, v = u[keep], v[keep]
    z = depth[v, u]
    if depth_camera is not None:
        pixels = np.stack([u, v], 1).astype(np.float64)[:, None]
        normalised = cv2.undistortPoints(pixels, depth_camera.matrix,
                                         depth_camera.distortion)[:, 0]
        points = np.concatenate([normalised * z[:, None], z[:, None]], 1)
        rigid = depth_camera.to_colour
        return torch.tensor(points @ rigid[:3, :3].T + rigid[:3, 3], dtype=torch.float32)
    height, width = depth.shape
    sx = width / (camera.width or COLOR_SIZE[0])
    sy = height / (camera.height or COLOR_SIZE[1])
    # OpenCV centres pixel u at u: a depth pixel's centre is (u + 0.5) / s - 0.5 in the
    # colour image, so the principal point scales as (c + 0.5) s - 0.5, not c s
    scaled = Camera(camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5,
                    (camera.cy + 0.5) * sy - 0.5)
    return scaled.backproject(torch.tensor(u, dtype=torch.float32),
                              torch.tensor(v, dtype=torch.float32),
                              torch.tensor(z, dtype=torch.float32))
