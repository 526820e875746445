"""Depth input (SMPLify-D / PROX-D): back-projection of body-mask pixels and the depth term."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from prox_engine.camera import Camera
from prox_engine.depth import load_depth_points
from prox_engine.errors import InputError
from prox_engine.geometry import vertex_normals
from prox_engine.losses import depth_data


def _frames(tmp_path, width=64, height=36):
    depth = np.full((height, width), 2000 * 8, dtype=np.uint16)  # 2 m everywhere
    mask = np.full((height, width), 255, dtype=np.uint8)
    mask[10:20, 5:15] = 0  # body 0 on the left half of the image
    Image.fromarray(depth).save(tmp_path / "d.png")
    Image.fromarray(mask).save(tmp_path / "m.png")
    return tmp_path / "d.png", tmp_path / "m.png"


def test_depth_points_are_back_projected_mask_pixels(tmp_path):
    camera = Camera(fx=64.0, fy=64.0, cx=32.0, cy=18.0, width=64, height=36)
    points = load_depth_points(*_frames(tmp_path), camera, flip=False, max_points=1000)
    assert points.shape == (100, 3)
    assert torch.allclose(points[:, 2], torch.full((100,), 2.0))
    assert torch.all(points[:, 0] < 0)  # left of the optical centre
    flipped = load_depth_points(*_frames(tmp_path), camera, flip=True, max_points=1000)
    assert torch.all(flipped[:, 0] > 0)
    few = load_depth_points(*_frames(tmp_path), camera, flip=False, max_points=10)
    assert few.shape == (10, 3)


def test_depth_registered_at_another_size_reads_each_pixel_at_its_centre(tmp_path):
    """A depth frame registered to the colour camera at a third of its size (as Kinect
    tools write it): a depth pixel covers colour pixels, its centre at ``(u + 0.5) / s -
    0.5`` in the colour camera's OpenCV coordinates. Pixels of a plane tilted to the
    camera, written so, are read back onto the plane; read as ``u / s``, each is off its
    ray by a pixel of the colour camera, and the points off the plane by millimetres."""
    camera = Camera(fx=300.0, fy=310.0, cx=97.3, cy=61.8, width=192, height=108)
    s = 1 / 3
    height, width = 36, 64
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = ((u + 0.5) / s - 0.5 - camera.cx) / camera.fx  # the ray of each depth pixel's centre
    y = ((v + 0.5) / s - 0.5 - camera.cy) / camera.fy
    normal, offset = np.array([0.6, 0.5, 1.0]), 2.0  # the plane n . p = offset
    z = offset / (normal[0] * x + normal[1] * y + normal[2])
    Image.fromarray(np.round(z * 8000).astype(np.uint16)).save(tmp_path / "d.png")
    Image.fromarray(np.zeros((height, width), dtype=np.uint8)).save(tmp_path / "m.png")
    points = load_depth_points(tmp_path / "d.png", tmp_path / "m.png", camera, flip=False,
                               max_points=10000).double().numpy()
    off = np.abs(points @ normal - offset) / np.linalg.norm(normal)
    assert off.max() < 1e-3  # the PNG's 1/8 mm steps and float32


def test_depth_mask_size_mismatch(tmp_path):
    depth, _ = _frames(tmp_path)
    Image.fromarray(np.zeros((5, 5), dtype=np.uint8)).save(tmp_path / "small.png")
    with pytest.raises(InputError, match="does not match"):
        load_depth_points(depth, tmp_path / "small.png", Camera(1, 1, 0, 0), False, 10)


def test_depth_term_is_zero_on_the_surface_and_grows_off_it(body):
    params = body.init_params(1)
    params["transl"][0, 2] = 3.0
    params["global_orient"][0] = torch.tensor([torch.pi / 2, 0.0, 0.0])  # upright, facing us
    out = body(params)
    visible = ((vertex_normals(out.vertices, body.faces)[0] * out.vertices[0]).sum(-1) < 0)
    cloud = out.vertices[0, visible & body.scene_vertices][::50]
    on = depth_data(out, body, [cloud], rho=0.05)
    off = depth_data(out, body, [cloud + torch.tensor([0.0, 0.0, 0.05])], rho=0.05)
    assert on.item() < 1e-6 and off.item() > 100 * on.item()


def _view(angles: tuple[float, float, float], offset: list[float]) -> np.ndarray:
    from prox_engine.geometry import axis_angle_to_matrix

    view = np.eye(4)
    view[:3, :3] = axis_angle_to_matrix(torch.tensor(angles)).numpy()
    view[:3, 3] = offset
    return view


def test_kinect_depth_through_its_ir_calibration_lands_on_the_body(tmp_path, body):
    """A body seen by a Kinect-like depth camera (512x424, distorted, turned and offset
    from the colour camera, whose own view_mtx is not the identity either) is written as
    PROX writes depth (mm x 8) with a body-index mask; read back through IR.json, every
    point lies on the body in the colour camera's frame within 1 cm. Taking the same
    frame as registered to the colour camera misses the body by far more."""
    import json

    import cv2

    from prox_engine.dataset import Recording, load_depth_camera

    params = body.init_params(1)
    params["global_orient"][0] = torch.tensor([-np.pi / 2, 0.0, 0.0])  # upright, facing us
    params["transl"][0] = torch.tensor([0.1, 0.2, 2.5])
    with torch.no_grad():
        colour_points = body(params).vertices[0].numpy().astype(np.float64)
    colour_view = _view((0.02, -0.03, 0.01), [0.03, -0.01, 0.02])
    ir_view = _view((0.03, 0.06, -0.02), [-0.052, 0.004, 0.011])
    matrix = np.array([[365.6, 0.0, 257.2], [0.0, 365.6, 206.9], [0.0, 0.0, 1.0]])
    distortion = np.array([0.092, -0.271, 0.0012, -0.0021, 0.091])
    common = (colour_points - colour_view[:3, 3]) @ colour_view[:3, :3]
    ir_points = common @ ir_view[:3, :3].T + ir_view[:3, 3]
    pixels, _ = cv2.projectPoints(ir_points, np.zeros(3), np.zeros(3), matrix, distortion)
    u, v = np.round(pixels[:, 0]).astype(int).T
    depth = np.zeros((424, 512), dtype=np.uint16)
    for x, y, z in sorted(zip(u, v, ir_points[:, 2]), key=lambda row: -row[2]):
        if 0 <= x < 512 and 0 <= y < 424:
            depth[y, x] = round(z * 8000)  # nearest last: a z-buffer
    mask = np.where(depth > 0, 0, 255).astype(np.uint8)
    rec = "Room_00000_01"
    for folder in (f"recordings/{rec}/Depth", f"recordings/{rec}/BodyIndex", "calibration"):
        (tmp_path / folder).mkdir(parents=True)
    Image.fromarray(depth).save(tmp_path / f"recordings/{rec}/Depth/f.png")
    Image.fromarray(mask).save(tmp_path / f"recordings/{rec}/BodyIndex/f.png")
    (tmp_path / "calibration" / "Color.json").write_text(json.dumps({
        "f": [1060.5, 1060.4], "c": [951.3, 536.8], "k": [0.0] * 5,
        "view_mtx": colour_view[:3].tolist()}))
    (tmp_path / "calibration" / "IR.json").write_text(json.dumps({
        "camera_mtx": matrix.tolist(), "k": distortion.tolist(),
        "view_mtx": ir_view[:3].tolist()}))

    recording = Recording(tmp_path, rec)
    assert recording.depth_calibration_path.name == "IR.json"
    colour = Camera(1060.5, 1060.4, 951.3, 536.8)
    depth_camera = load_depth_camera(recording.depth_calibration_path,
                                     tmp_path / "calibration" / "Color.json")
    points = load_depth_points(*recording.depth_paths("f"), colour, flip=False,
                               max_points=3000, depth_camera=depth_camera)
    vertices = torch.tensor(colour_points, dtype=torch.float32)
    assert len(points) == 3000
    assert float(torch.cdist(points, vertices).min(1).values.max()) < 0.01
    registered = load_depth_points(*recording.depth_paths("f"), colour, flip=False,
                                   max_points=3000)
    assert float(torch.cdist(registered, vertices).min(1).values.median()) > 0.05


@pytest.mark.parametrize("content, problem", [
    ('{"k": [0, 0, 0, 0, 0]}', "needs 'camera_mtx'"),
    ('{"camera_mtx": [1, 0, 0, 0, 1, 0, 0, 0, 1], "view_mtx": [1, 2]}',
     "'view_mtx' must have 12 numbers"),
    ("not json", "not valid JSON")])
def test_bad_depth_calibration_names_the_file(tmp_path, content, problem):
    from prox_engine.dataset import load_depth_camera

    (tmp_path / "IR.json").write_text(content)
    (tmp_path / "Color.json").write_text('{"f": [1000, 1000], "c": [960, 540]}')
    with pytest.raises(InputError, match=problem) as error:
        load_depth_camera(tmp_path / "IR.json", tmp_path / "Color.json")
    assert error.value.path.endswith("IR.json")


def test_a_tall_person_starts_at_the_depth_clouds_distance(body):
    """Keypoints alone put a person much taller than the prior's mean too close to a
    tilted camera (0.8 m here), and the robust depth term, saturated that far off, barely
    pulls. Before the first stage with the depth term each body is scaled about the camera
    centre to the depth cloud's distance: the fit ends within 5 cm of the true depth."""
    from prox_engine.config import FitConfig, Stage
    from prox_engine.fitting import Fitter, Frame
    from prox_engine.keypoints import N_KEYPOINTS, Keypoints

    from .test_fitting import CAMERA, tilted_camera, world_to_camera

    cam2world = tilted_camera()
    params = body.init_params(1)
    params["shape"][0, 4] = 3.0  # height: about the tallest adults
    to_camera = cam2world[:2, 3] - np.array([0.2, 0.3])
    params["global_orient"][0] = torch.tensor([0.0, 0.0, float(np.arctan2(to_camera[0], -to_camera[1]))])
    with torch.no_grad():
        out = body(params)
    world = out.vertices[0] - out.vertices[0].mean(0) + torch.tensor([0.2, 0.3, 1.0])
    vertices = world_to_camera(world, cam2world)
    keypoints = world_to_camera(out.keypoints[0] - out.vertices[0].mean(0)
                                + torch.tensor([0.2, 0.3, 1.0]), cam2world)
    facing = (vertex_normals(vertices[None], body.faces)[0] * vertices).sum(-1) < 0
    cloud = vertices[facing & body.scene_vertices][::10]
    data = np.zeros((N_KEYPOINTS, 3))
    data[:25, :2] = CAMERA.project(keypoints[:25]).numpy()
    data[:25, 2] = 0.9
    frame = Frame("f", Keypoints(data, has_hands=False, has_face=False), cloud)
    config = FitConfig("depth", [
        Stage("global", {"body": 1.0, "pose_prior": 30.0, "shape": 30.0, "bending": 30.0}),
        Stage("body", {"body": 1.0, "pose_prior": 10.0, "shape": 10.0, "bending": 10.0,
                       "depth": 1e5})], arm_restarts=False)
    result = Fitter(body, CAMERA, config).fit([frame])[0]
    torso = [2, 5, 9, 12]
    error = abs(float(result.keypoints[torso, 2].mean() - keypoints[torso, 2].mean()))
    assert error < 0.05, error
