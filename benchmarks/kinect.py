"""The Kinect depth camera as PROX ships its recordings: ``calibration/IR.json`` and, per
frame, ``Depth/<frame>.png`` (the 512x424 depth camera's view, millimetres x 8, not
registered to the colour camera) with ``BodyIndex/<frame>.png`` (0 on the person, 255 off).

The depth camera sits 5 cm beside the colour camera, turned by about a degree, with a
Kinect v2's lens distortion. Depth is rendered with a pinhole camera and then distorted
(each output pixel looks up where its undistorted ray falls); what a Kinect adds: axial
noise growing with distance, pixels lost at the silhouette, and dropouts in small patches.

The depth must not agree with the scan by construction (the fitter re-registers the scan
from it): ``IR.json`` is written a few millimetres and a fraction of a degree off the
true colour-to-depth pose, as a stereo calibration is; the sensor's range is off by a
small scale and offset; and the live room holds clutter the scan lacks (boxes and bags
on the floor).
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from trimesh.transformations import rotation_matrix

from prox_engine.camera import Camera
from prox_engine.output import atomic_write_text
from prox_engine.render import BodyMesh, SceneRenderer

WIDTH, HEIGHT = 512, 424
MATRIX = np.array([[365.6, 0.0, 257.2], [0.0, 365.6, 206.9], [0.0, 0.0, 1.0]])
DISTORTION = np.array([0.092, -0.271, 0.0012, -0.0021, 0.091])
DEPTH_SCALE = 8000.0  # metres -> PNG value (mm x 8)
NOISE = 0.0004  # axial noise sigma at 1 m (m); it grows with the square of the depth
CALIBRATION_ERROR = ((0.002, 0.005), (0.1, 0.3))  # written IR pose: metres, degrees off
RANGE_SCALE, RANGE_OFFSET = 0.003, 0.003  # per recording: sigma of the range's scale, (m)
CLUTTER = (1, 4)  # unscanned boxes on the floor, 0.15-0.5 m, at least 0.5 m from the person


def _colour_to_depth() -> np.ndarray:
    """The rigid transform (4, 4) taking colour-camera points to the depth camera's frame:
    ``IR.json``'s ``view_mtx`` when ``Color.json`` has none (the colour frame is common)."""
    view = np.eye(4)
    view[:3, :3] = Rotation.from_rotvec([0.004, 0.015, -0.006]).as_matrix()
    view[:3, 3] = [-0.052, 0.0005, 0.002]
    return view


COLOUR_TO_DEPTH = _colour_to_depth()


def rigid_error(rng: np.random.Generator, metres: tuple[float, float],
                 degrees: tuple[float, float]) -> np.ndarray:
    """A rigid transform (4, 4): a shift of ``metres`` and a turn of ``degrees`` (ranges)
    in random directions."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    error = np.eye(4)
    error[:3, :3] = Rotation.from_rotvec(
        axis / np.linalg.norm(axis) * np.radians(rng.uniform(*degrees))).as_matrix()
    error[:3, 3] = shift / np.linalg.norm(shift) * rng.uniform(*metres)
    return error


def write_calibration(out: Path, rng: np.random.Generator) -> None:
    """``calibration/IR.json``, shared by the recordings of a base directory, its
    colour-to-depth pose off by CALIBRATION_ERROR."""
    (out / "calibration").mkdir(parents=True, exist_ok=True)
    written = rigid_error(rng, *CALIBRATION_ERROR) @ COLOUR_TO_DEPTH
    atomic_write_text(out / "calibration" / "IR.json", json.dumps({
        "camera_mtx": MATRIX.tolist(), "k": DISTORTION.tolist(),
        "view_mtx": written[:3].tolist()}))


def clutter(scene: trimesh.Trimesh, people: np.ndarray, rng: np.random.Generator
            ) -> list[trimesh.Trimesh]:
    """Boxes standing on the scan's floor (its lowest upward faces) that the scan lacks,
    0.5 m or more from the person (world-frame vertices ``people``)."""
    up = scene.face_normals[:, 2] > 0.95
    centres = scene.triangles_center
    floor = up & (centres[:, 2] < scene.bounds[0, 2] + 0.05)
    # 0.35 m: half the largest box's diagonal
    clear = cKDTree(people[:, :2]).query(centres[:, :2])[0] > 0.5 + 0.35
    candidates = np.flatnonzero(floor & clear)
    boxes = []
    for face in rng.choice(candidates, min(len(candidates), int(rng.integers(*CLUTTER))),
                           replace=False):
        size = rng.uniform(0.15, 0.5, 3)
        box = trimesh.creation.box(size)
        box.apply_transform(rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1]))
        box.apply_translation(centres[face] + [0, 0, size[2] / 2])
        boxes.append(box)
    return boxes


def write_depth(out: Path, rec: str, frames: list[tuple[str, np.ndarray]], faces: np.ndarray,
                scene: trimesh.Trimesh, cam2world: np.ndarray, rng: np.random.Generator
                ) -> None:
    """Depth and body-index frames of the true bodies (world-frame vertices per frame) in
    the scene plus unscanned :func:`clutter`, seen from the depth camera of a colour camera
    at ``cam2world``, with a range error of the recording's own."""
    depth_pose = cam2world @ np.linalg.inv(COLOUR_TO_DEPTH)
    pinhole = Camera(MATRIX[0, 0], MATRIX[1, 1], MATRIX[0, 2], MATRIX[1, 2], width=WIDTH,
                     height=HEIGHT)
    every = np.concatenate([v for _, v in frames])
    live = trimesh.util.concatenate([scene, *clutter(scene, every, rng)])
    scale, offset = 1 + rng.normal(0, RANGE_SCALE), rng.normal(0, RANGE_OFFSET)
    renderer = SceneRenderer(live.vertices, live.faces, None, pinhole, depth_pose,
                             np.stack([every.min(0), every.max(0)]), WIDTH, HEIGHT)
    lookup = _undistorted_pixels()
    folders = [out / "recordings" / rec / name for name in ("Depth", "BodyIndex")]
    for folder in folders:
        folder.mkdir(parents=True, exist_ok=True)
    try:
        for name, vertices in frames:
            seen, body = renderer.depth("camera", [BodyMesh(vertices, faces)])
            seen, body = seen[lookup], body[lookup]  # distorted, as the lens sees
            person = (body > 0) & (np.abs(seen - body) < 0.01)  # not behind furniture
            depth = (seen * scale + offset
                     + rng.normal(0.0, 1.0, seen.shape) * NOISE * seen ** 2)
            lost = _silhouette(person) & (rng.random(person.shape) < 0.5)
            lost |= _patches(rng, person.shape)
            depth[lost | (seen <= 0)] = 0.0
            Image.fromarray(np.round(depth * DEPTH_SCALE).astype(np.uint16)).save(
                folders[0] / f"{name}.png")
            Image.fromarray(np.where(person & ~lost, 0, 255).astype(np.uint8)).save(
                folders[1] / f"{name}.png")
    finally:
        renderer.close()


def _undistorted_pixels() -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted depth image, the (row, column) of the pinhole image
    its ray falls on (clipped to the image)."""
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(np.float64)[:, None]
    normalised = cv2.undistortPoints(pixels, MATRIX, DISTORTION)[:, 0]
    column = np.clip(np.round(MATRIX[0, 0] * normalised[:, 0] + MATRIX[0, 2]), 0, WIDTH - 1)
    row = np.clip(np.round(MATRIX[1, 1] * normalised[:, 1] + MATRIX[1, 2]), 0, HEIGHT - 1)
    return row.astype(int).reshape(HEIGHT, WIDTH), column.astype(int).reshape(HEIGHT, WIDTH)


def _silhouette(mask: np.ndarray) -> np.ndarray:
    """Pixels of ``mask`` with a 4-neighbour outside it."""
    padded = np.pad(mask, 1)
    inner = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    return mask & ~inner


def _patches(rng: np.random.Generator, shape: tuple[int, int], count: int = 12
             ) -> np.ndarray:
    """Small holes (2-6 px squares) where the sensor returned nothing."""
    holes = np.zeros(shape, dtype=bool)
    for _ in range(count):
        size = int(rng.integers(2, 7))
        top, left = int(rng.integers(0, shape[0] - size)), int(rng.integers(0, shape[1] - size))
        holes[top:top + size, left:left + size] = True
    return holes
