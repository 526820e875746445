"""How far the colour-to-depth calibration (``calibration/IR.json``) is off, read where the
person is: each frame's body depth points, taken into the colour camera through
``IR.json`` as the fitter takes them, aligned to a body (its vertices that face the
camera) by a turn about the colour camera (pitch and yaw) and a scale about it (which
takes up the depth the keypoints leave open). With the true bodies the reading is the
calibration's error as it moves the person, its shift included; with fitted bodies their
own errors add to it (docs/benchmark.md). A probe of the benchmark, not part of the fitter.

    .venv/bin/python -m benchmarks.calibration_reading bench_output/data \\
        --fits bench_output/fits/prox --parts limbs
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from prox_engine.body.anny_body import AnnyBody
from prox_engine.dataset import Recording, load_calibration, load_depth_camera
from prox_engine.depth import load_depth_points

from . import kinect

# The parts whose keypoints the detector does not offset alike for every person: without
# the trunk, whose hips OpenPose puts above the model's (benchmarks.detector)
LIMBS = ("head", "left_thigh", "right_thigh", "left_shin", "right_shin", "left_upper_arm",
         "right_upper_arm", "left_forearm", "right_forearm", "left_foot", "right_foot")
ITERATIONS = 15
POINTS = 3000  # depth points a frame
FAR_M = 0.1  # a point farther than this from the body gets no weight


def read_turn(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
              parts: np.ndarray | None = None) -> np.ndarray:
    """The turn (pitch, yaw; radians about the colour camera's x and y axes) that, with a
    scale about the camera, best lays the colour-frame depth ``points`` (N, 3) on the body
    (``vertices`` (V, 3) colour frame, ``faces``): robust point-to-plane against the
    vertices facing the camera, ``parts`` (V,) bool keeping some of them and the points
    nearest those."""
    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    front = (normals * vertices).sum(1) < 0
    if parts is not None:
        _, nearest = cKDTree(vertices[front]).query(points)
        points = points[parts[front][nearest]]
        front &= parts
    tree = cKDTree(vertices[front])
    targets, target_normals = vertices[front], normals[front]
    turn, scale = np.zeros(3), 1.0
    for _ in range(ITERATIONS):
        moved = scale * points @ Rotation.from_rotvec(turn).as_matrix().T
        distance, index = tree.query(moved)
        q, n = targets[index], target_normals[index]
        residual = ((moved - q) * n).sum(1)
        jacobian = np.concatenate([np.cross(moved, n)[:, :2], (n * moved).sum(1)[:, None]], 1)
        sigma = max(1.4826 * float(np.median(np.abs(residual))), 0.003)
        weight = np.minimum(1.0, 2 * sigma / np.maximum(np.abs(residual), 1e-12))
        weight = weight * (distance < FAR_M)
        step = np.linalg.solve(jacobian.T @ (jacobian * weight[:, None]) + 1e-9 * np.eye(3),
                               -jacobian.T @ (residual * weight))
        turn = (Rotation.from_rotvec([step[0], step[1], 0.0])
                * Rotation.from_rotvec(turn)).as_rotvec()
        scale *= 1 + step[2]
    return turn[:2]


def correction(base: Path) -> np.ndarray:
    """The rigid transform (4, 4) that takes points read through ``base``'s ``IR.json`` (as
    the fitter reads it) to where the true colour-to-depth pose
    (``kinect.COLOUR_TO_DEPTH``) puts them."""
    calibration = Path(base) / "calibration"
    read = load_depth_camera(calibration / "IR.json", calibration / "Color.json").to_colour
    return np.linalg.inv(kinect.COLOUR_TO_DEPTH) @ np.linalg.inv(read)


def recording_turns(base: Path, recording: str, body: AnnyBody, fits: Path | None = None,
                    parts: tuple[str, ...] | None = None) -> np.ndarray:
    """Each frame's :func:`read_turn` (F, 2) of ``recording``, against its true bodies or,
    given ``fits`` (a ``prox fit`` output folder), the fitted ones."""
    rec = Recording(Path(base), recording)
    camera = load_calibration(rec.calibration_path)
    depth_camera = load_depth_camera(rec.depth_calibration_path, rec.calibration_path)
    faces = body.faces.numpy()
    keep = None if parts is None else np.isin(np.asarray(body.vertex_parts), parts)
    turns = []
    for name in rec.frames():
        points = load_depth_points(*rec.depth_paths(name), camera, False, POINTS,
                                   depth_camera=depth_camera).double().numpy()
        if fits is None:
            vertices = np.load(Path(base) / "ground_truth" / recording / f"{name}.npz"
                               )["vertices"]
        else:
            vertices = np.asarray(trimesh.load(Path(fits) / recording / "meshes" / name
                                               / "000.ply", process=False).vertices)
        turns.append(read_turn(points, np.asarray(vertices, dtype=np.float64), faces, keep))
    return np.array(turns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path, help="a benchmark's generated data folder")
    parser.add_argument("--fits", type=Path, help="fits to align to (default: the truth)")
    parser.add_argument("--parts", choices=("all", "limbs"), default="all")
    args = parser.parse_args()
    body = AnnyBody.load()
    parts = LIMBS if args.parts == "limbs" else None
    ahead = np.array([0.0, 0.5, 3.0])  # a point 3 m ahead and 0.5 m below the camera
    exact = correction(args.data)
    print(f"IR.json's error moves a point 3 m ahead by "
          f"{np.round(1000 * (exact[:3, :3] @ ahead + exact[:3, 3] - ahead), 1)} mm")
    every = []
    for recording in sorted(p.name for p in (args.data / "ground_truth").iterdir()):
        turns = recording_turns(args.data, recording, body, args.fits, parts)
        every.append(turns)
        pitch, yaw = 1000 * np.median(turns, 0)
        print(f"{recording:<26} pitch {pitch:+7.2f} yaw {yaw:+7.2f} mrad")
    pitch, yaw = np.median(np.concatenate(every), 0)
    moved = Rotation.from_rotvec([pitch, yaw, 0.0]).as_matrix() @ ahead - ahead
    print(f"pooled: pitch {1000 * pitch:+.2f} yaw {1000 * yaw:+.2f} mrad, which moves it by "
          f"{np.round(1000 * moved, 1)} mm")


if __name__ == "__main__":
    main()
