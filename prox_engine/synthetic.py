"""A small synthetic PROX-layout data set: a scan-like room with a chair and a person
sitting on it, seen by a Kinect-like camera, with OpenPose-like keypoints.

Used by ``make demo`` and the tests. Ground truth goes to ``<out>/ground_truth/``, beside
the layout the fitter reads, never inside it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from .body.anny_body import BODY_BONES, AnnyBody
from .geometry import axis_angle_to_matrix
from .keypoints import BODY, LEFT_HAND, N_BODY, RIGHT_HAND
from .output import atomic_write_text

SCENE = "Synthetic"
WIDTH, HEIGHT = 1920, 1080
INTRINSICS = {"f": [1060.53, 1060.38], "c": [951.30, 536.77]}


def sitting_pose(phase: float = 0.0) -> dict[str, list[float]]:
    """Bone rotations (local-bone axis-angle) of a person sitting upright, hands on thighs;
    ``phase`` moves the arms and head a little for sequences."""
    s = float(np.sin(phase))
    return {
        "upperleg01.L": [-1.5, 0.0, -0.08], "upperleg01.R": [-1.5, 0.0, 0.08],
        "lowerleg01.L": [1.45, 0.0, 0.0], "lowerleg01.R": [1.45, 0.0, 0.0],
        "upperarm01.L": [0.35 + 0.1 * s, 0.0, -0.55], "upperarm01.R": [0.35 - 0.1 * s, 0.0, 0.55],
        "lowerarm01.L": [0.9 + 0.15 * s, 0.0, 0.0], "lowerarm01.R": [0.9, 0.0, 0.0],
        "spine03": [0.05, 0.0, 0.0], "head": [0.1 * s, 0.15 * s, 0.0],
    }


def _params(body: AnnyBody, pose: dict[str, list[float]], yaw: float,
            phenotype: dict[str, float]) -> dict[str, torch.Tensor]:
    params = body.init_params(1)
    for bone, value in pose.items():
        params["body_pose"][0, BODY_BONES.index(bone)] = torch.tensor(value)
    params["global_orient"][0] = torch.tensor([0.0, 0.0, yaw])
    for i, name in enumerate(["gender", "age", "muscle", "weight", "height", "proportions"]):
        if name in phenotype:
            params["shape"][0, i] = torch.logit(torch.tensor(phenotype[name]))
    return params


def _open_box(extents: list[float], centre: list[float]) -> trimesh.Trimesh:
    """A box surface without its bottom (scans never see under furniture)."""
    box = trimesh.creation.box(extents)
    box.vertices += centre
    box.update_faces(box.face_normals[:, 2] > -0.5)
    box.remove_unreferenced_vertices()
    return box


def _room(extents: list[float]) -> trimesh.Trimesh:
    """Floor and walls seen from inside (normals inward), no ceiling, floor at z = 0."""
    room = trimesh.creation.box(extents)
    room.vertices += [0.0, 0.0, extents[2] / 2]
    room.update_faces(room.triangles_center[:, 2] < extents[2] - 1e-6)  # drop the ceiling
    room.remove_unreferenced_vertices()
    room.invert()
    return room


def _look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world pose (x right, y down, z forward) in a z-up world."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], 1)
    pose[:3, 3] = position
    return pose


def make_sitting_dataset(out: Path, frames: int = 3, seed: int = 0, noise_px: float = 2.0,
                         face_size: float = 0.06, body: AnnyBody | None = None) -> Path:
    """Write a room + chair + sitting person data set in the PROX layout under ``out``."""
    out = Path(out)
    rng = np.random.default_rng(seed)
    body = body or AnnyBody.load()
    # A small woman: the mean-shape prior makes monocular fits place her too far away,
    # into the chair back, which is the ambiguity the scene terms resolve.
    phenotype = {"gender": 0.8, "age": float(torch.sigmoid(body.shape_init[0, 1])),
                 "height": 0.25, "weight": 0.45}
    yaw = 0.3
    rec = f"{SCENE}_00000_01"
    world_vertices = []
    gt_params = []
    for t in range(frames):
        params = _params(body, sitting_pose(0.6 * t), yaw, phenotype)
        with torch.no_grad():
            world_vertices.append(body(params).vertices[0].numpy())
        gt_params.append(params)
    # Put the first frame's feet on the floor, centred at (0, 0).
    v0 = world_vertices[0]
    shift = np.array([-v0[:, 0].mean(), -v0[:, 1].mean(), -v0[:, 2].min()])
    world_vertices = [v + shift for v in world_vertices]
    for p in gt_params:
        p["transl"][0] = torch.tensor(shift, dtype=torch.float32)

    # Chair under the buttocks and thighs, backrest against the back, in the body's frame.
    rot = axis_angle_to_matrix(torch.tensor([0.0, 0.0, yaw])).numpy()
    local = (world_vertices[0] - shift) @ rot  # undo the yaw: body faces -y, left is +x
    main = body.scene_vertices.numpy()
    parts = np.asarray(body.vertex_parts)
    body_local = local[main]
    width = 0.5
    # Seat from just behind the calves to the back, its top just under every body vertex
    # over it; backrest just behind the back: the person touches but does not penetrate.
    legs = np.isin(parts[main], ["left_shin", "right_shin", "left_foot", "right_foot"])
    seat_front = float(body_local[legs, 1].max()) + 0.01
    over = (np.abs(body_local[:, 0]) < width / 2) & (body_local[:, 1] > seat_front)
    seat_top = float(body_local[over, 2].min()) - 0.003
    back_y = float(body_local[over & (body_local[:, 2] > seat_top + 0.05), 1].max()) + 0.003
    floor = float(body_local[:, 2].min())
    seat_depth = back_y - seat_front
    seat_y = back_y - seat_depth / 2
    seat_h = seat_top - floor
    parts_local = [
        _open_box([width, seat_depth, seat_h], [0.0, seat_y, floor + seat_h / 2]),
        _open_box([width, 0.04, 0.55], [0.0, back_y + 0.02, seat_top + 0.3]),
    ]
    chair = trimesh.util.concatenate(parts_local)
    chair.vertices = chair.vertices @ rot.T + shift
    room = _room([6.0, 6.0, 3.0])
    table = _open_box([1.2, 0.7, 0.75], [-1.8, -1.2, 0.375])
    scene = trimesh.util.concatenate([room, chair, table])
    scene = scene.subdivide_to_size(face_size)
    scene.vertices += rng.normal(0.0, 0.002, scene.vertices.shape)

    # Camera 2.6 m in front of the person at 1.3 m height.
    facing = rot @ np.array([0.0, -1.0, 0.0])
    centre = world_vertices[0][main].mean(0)
    cam2world = _look_at(centre + 2.6 * facing + np.array([0.4, 0.0, 1.3 - centre[2]]), centre)

    (out / "scenes").mkdir(parents=True, exist_ok=True)
    scene.export(out / "scenes" / f"{SCENE}.ply")
    for folder, name, content in (("cam2world", f"{SCENE}.json", cam2world.tolist()),
                                  ("calibration", "Color.json", INTRINSICS)):
        (out / folder).mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / folder / name, json.dumps(content))
    (out / "recordings" / rec).mkdir(parents=True, exist_ok=True)
    kp_dir = out / "keypoints" / rec
    kp_dir.mkdir(parents=True, exist_ok=True)
    gt_dir = out / "ground_truth" / rec
    gt_dir.mkdir(parents=True, exist_ok=True)
    world2cam = np.linalg.inv(cam2world)
    f, c = INTRINSICS["f"], INTRINSICS["c"]
    for t, params in enumerate(gt_params):
        with torch.no_grad():
            out_t = body(params)
        kp_world = out_t.keypoints[0].numpy()  # the body's frame is the world frame here
        kp_cam = kp_world @ world2cam[:3, :3].T + world2cam[:3, 3]
        uv = kp_cam[:, :2] / kp_cam[:, 2:] * f + c
        uv += rng.normal(0.0, noise_px, uv.shape)
        conf = rng.uniform(0.65, 0.95, len(uv))
        people = {
            "pose_keypoints_2d": _flat(uv[BODY], conf[BODY]),
            "hand_left_keypoints_2d": _flat(uv[LEFT_HAND], conf[LEFT_HAND] * 0.6),
            "hand_right_keypoints_2d": _flat(uv[RIGHT_HAND], conf[RIGHT_HAND] * 0.6),
        }
        frame = f"s001_frame_{t + 1:05d}__00.00.{t:02d}.000"
        atomic_write_text(kp_dir / f"{frame}_keypoints.json",
                          json.dumps({"version": 1.3, "people": [people]}))
        verts_cam = world_vertices[t] @ world2cam[:3, :3].T + world2cam[:3, 3]
        joints_cam = kp_cam[:N_BODY]
        np.savez(gt_dir / f"{frame}.npz", vertices=verts_cam.astype(np.float32),
                 joints=joints_cam.astype(np.float32))
    return out


def _flat(uv: np.ndarray, conf: np.ndarray) -> list[float]:
    return np.concatenate([uv, conf[:, None]], 1).reshape(-1).round(3).tolist()
