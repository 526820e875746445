"""A small synthetic PROX-layout data set: a scan-like room with a chair and a person
sitting on it, seen by a Kinect-like camera, with OpenPose-like keypoints.

Used by ``make demo`` and the tests; the helpers also build ``benchmarks.generate``. Ground
truth goes to ``<out>/ground_truth/``, beside the layout the fitter reads, never inside it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
import trimesh

from .body.anny_body import BODY_BONES, PHENOTYPES, AnnyBody
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


def body_params(body: AnnyBody, pose: dict[str, list[float]], yaw: float,
                phenotype: dict[str, float]) -> dict[str, torch.Tensor]:
    """anny parameters for a pose (bone -> local axis-angle), a yaw about z and a phenotype
    (names of ``PHENOTYPES`` -> values in [0, 1]; missing ones keep the body's mean)."""
    params = body.init_params(1)
    for bone, value in pose.items():
        params["body_pose"][0, BODY_BONES.index(bone)] = torch.tensor(value)
    params["global_orient"][0] = torch.tensor([0.0, 0.0, yaw])
    for i, name in enumerate(PHENOTYPES):
        if name in phenotype:
            params["shape"][0, i] = torch.logit(torch.tensor(phenotype[name]))
    return params


def open_box(extents: list[float], centre: list[float], bottom: bool = False) -> trimesh.Trimesh:
    """A box surface, without its bottom unless ``bottom`` (scans never see under furniture;
    a table top needs one so that knees under it are outside)."""
    box = trimesh.creation.box(extents)
    box.vertices += centre
    if not bottom:
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


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world pose (x right, y down, z forward) in a z-up world."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], 1)
    pose[:3, 3] = position
    return pose


def chair(local: np.ndarray, parts: np.ndarray, width: float = 0.5,
          backrest: bool = True, cushion: float = 0.0) -> trimesh.Trimesh:
    """A seat (and backrest) fitted to sitting body points ``local`` (N, 3) labelled with
    their ``parts``, in the body's frame (facing -y, left +x, centred on x = 0).

    The seat runs from just behind the calves to the back, its top just under every body
    point over it; the backrest is just behind the back: the person touches but does not
    penetrate the chair."""
    legs = np.isin(parts, ["left_shin", "right_shin", "left_foot", "right_foot"])
    seat_front = float(local[legs, 1].max()) + 0.01
    over = (np.abs(local[:, 0]) < width / 2) & (local[:, 1] > seat_front)
    seat_top = float(local[over, 2].min()) - 0.003
    back_y = float(local[over & (local[:, 2] > seat_top + 0.05), 1].max()) + 0.003
    seat_top += cushion  # a soft seat, scanned before it was sat on: the body sinks in
    floor = float(local[:, 2].min())
    seat_depth = back_y - seat_front
    seat_h = seat_top - floor
    boxes = [open_box([width, seat_depth, seat_h], [0.0, back_y - seat_depth / 2,
                                                    floor + seat_h / 2])]
    if backrest:
        boxes.append(open_box([width, 0.04, 0.55], [0.0, back_y + 0.02, seat_top + 0.3]))
    return trimesh.util.concatenate(boxes)


FLOOR_WOOD, WALL_PAINT, FURNITURE = (0.56, 0.42, 0.30), (0.86, 0.84, 0.78), (0.42, 0.48, 0.58)
SKIN = (0.88, 0.62, 0.50)


def paint(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Give a synthetic scan vertex colours as a real scan has (PROX's do): wooden floor
    boards, painted walls, furniture in another colour; deterministic, so that painting
    draws nothing from a data set's random stream."""
    v, n = mesh.vertices, mesh.vertex_normals
    lo, hi = v.min(0), v.max(0)
    colours = np.tile(FURNITURE, (len(v), 1))
    wall = ((np.minimum(v[:, :2] - lo[:2], hi[:2] - v[:, :2]).min(1) < 0.05)
            & (np.abs(n[:, 2]) < 0.3))
    floor = (v[:, 2] < lo[2] + 0.03) & (n[:, 2] > 0.7)
    colours[wall] = WALL_PAINT
    boards = 0.92 + 0.08 * (np.floor(v[:, 0] / 0.15) % 2)  # 15 cm boards
    colours[floor] = np.outer(boards[floor], FLOOR_WOOD)
    mesh.visual.vertex_colors = np.column_stack([np.round(colours * 255),
                                                 np.full(len(v), 255)]).astype(np.uint8)
    return mesh


def write_photos(out: Path, rec: str, frames: list[tuple[str, np.ndarray]], faces: np.ndarray,
                 scene: trimesh.Trimesh, cam2world: np.ndarray) -> None:
    """``recordings/<rec>/Color/<frame>.jpg``: the scene and the true body (world-frame
    vertices per frame) as the camera saw them, slightly soft like a photograph."""
    from PIL import Image, ImageFilter

    from .camera import Camera
    from .render import BodyMesh, SceneRenderer

    colours = np.asarray(scene.visual.vertex_colors, dtype=float) / 255
    camera = Camera(*INTRINSICS["f"], *INTRINSICS["c"], width=WIDTH, height=HEIGHT)
    every = np.concatenate([v for _, v in frames])
    renderer = SceneRenderer(scene.vertices, scene.faces, colours, camera, cam2world,
                             np.stack([every.min(0), every.max(0)]), WIDTH, HEIGHT)
    folder = out / "recordings" / rec / "Color"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for name, vertices in frames:
            image = renderer.render("camera", [BodyMesh(vertices, faces, SKIN)])
            Image.fromarray(image).filter(ImageFilter.GaussianBlur(0.8)).save(
                folder / f"{name}.jpg", quality=88)
    finally:
        renderer.close()


def transform(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Points (..., 3) through a 4x4 rigid transform."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def project(points_cam: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of camera-frame points with ``INTRINSICS``."""
    f, c = np.asarray(INTRINSICS["f"]), np.asarray(INTRINSICS["c"])
    return points_cam[:, :2] / points_cam[:, 2:] * f + c


def openpose_person(uv: np.ndarray, conf: np.ndarray) -> dict[str, list[float]]:
    """An OpenPose ``people`` entry (body and hands, no face) from the 118-point layout."""
    return {
        "pose_keypoints_2d": _flat(uv[BODY], conf[BODY]),
        "hand_left_keypoints_2d": _flat(uv[LEFT_HAND], conf[LEFT_HAND]),
        "hand_right_keypoints_2d": _flat(uv[RIGHT_HAND], conf[RIGHT_HAND]),
    }


def frame_name(t: int) -> str:
    """PROX-style name of frame ``t`` (0-based)."""
    return f"s001_frame_{t + 1:05d}__00.00.{t:02d}.000"


def write_scene(out: Path, scene: str, mesh: trimesh.Trimesh, cam2world: np.ndarray) -> None:
    """The scan, camera pose and (shared) calibration of one scene in the PROX layout."""
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    mesh.export(out / "scenes" / f"{scene}.ply")
    for folder, name, content in (("cam2world", f"{scene}.json", cam2world.tolist()),
                                  ("calibration", "Color.json", INTRINSICS)):
        (out / folder).mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / folder / name, json.dumps(content))


def write_frame(out: Path, rec: str, frame: str, people: list[dict],
                vertices_cam: np.ndarray, joints_cam: np.ndarray) -> None:
    """One frame's OpenPose keypoints and its ground truth (camera-frame vertices and
    BODY_25 joints) in ``ground_truth/<rec>/<frame>.npz``."""
    for folder in ("recordings", "keypoints", "ground_truth"):
        (out / folder / rec).mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "keypoints" / rec / f"{frame}_keypoints.json",
                      json.dumps({"version": 1.3, "people": people}))
    np.savez(out / "ground_truth" / rec / f"{frame}.npz",
             vertices=vertices_cam.astype(np.float32), joints=joints_cam.astype(np.float32))


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
        params = body_params(body, sitting_pose(0.6 * t), yaw, phenotype)
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
    seat = chair(local[main], np.asarray(body.vertex_parts)[main])
    seat.vertices = seat.vertices @ rot.T + shift
    room = _room([6.0, 6.0, 3.0])
    table = open_box([1.2, 0.7, 0.75], [-1.8, -1.2, 0.375])
    scene = trimesh.util.concatenate([room, seat, table])
    scene = scene.subdivide_to_size(face_size)
    scene.vertices += rng.normal(0.0, 0.002, scene.vertices.shape)
    paint(scene)

    # Camera 2.6 m in front of the person at 1.3 m height.
    facing = rot @ np.array([0.0, -1.0, 0.0])
    centre = world_vertices[0][main].mean(0)
    cam2world = look_at(centre + 2.6 * facing + np.array([0.4, 0.0, 1.3 - centre[2]]), centre)
    write_scene(out, SCENE, scene, cam2world)
    world2cam = np.linalg.inv(cam2world)
    for t, params in enumerate(gt_params):
        with torch.no_grad():
            kp_cam = transform(body(params).keypoints[0].numpy(), world2cam)
        uv = project(kp_cam) + rng.normal(0.0, noise_px, (len(kp_cam), 2))
        conf = rng.uniform(0.65, 0.95, len(uv))
        conf[LEFT_HAND] *= 0.6
        conf[RIGHT_HAND] *= 0.6
        write_frame(out, rec, frame_name(t), [openpose_person(uv, conf)],
                    transform(world_vertices[t], world2cam), kp_cam[:N_BODY])
    write_photos(out, rec, [(frame_name(t), v) for t, v in enumerate(world_vertices)],
                 body.faces.numpy(), scene, cam2world)
    return out


def _flat(uv: np.ndarray, conf: np.ndarray) -> list[float]:
    return np.concatenate([uv, conf[:, None]], 1).reshape(-1).round(3).tolist()
