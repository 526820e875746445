"""Renders through OSMesa, checked pixel by pixel on known geometry: a closed room (floor,
walls, ceiling) and a box-shaped "body" standing in it."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from prox_engine.camera import Camera
from prox_engine.render import (AMBIENT, BASELINE_YELLOW, LIGHT_INTENSITY, NEAR,
                                PENETRATING_RED, SCENE_COLOUR, BodyMesh, SceneRenderer,
                                cut_away, face_normals, in_view)
from prox_engine.synthetic import look_at

WIDTH, HEIGHT = 480, 270
BODY_CENTRE = np.array([0.0, 0.0, 0.9])


@pytest.fixture(scope="module")
def room():
    """A closed 5 x 5 x 2.6 m room (seen from inside) and a 0.5 x 0.3 x 1.8 m body box."""
    walls = trimesh.creation.box([5.0, 5.0, 2.6])
    walls.vertices += [0.0, 0.0, 1.3]
    walls.invert()  # normals inwards, like a scan of a room
    walls = walls.subdivide_to_size(0.5)
    body = trimesh.creation.box([0.5, 0.3, 1.8])
    body.vertices += BODY_CENTRE
    camera = Camera(500.0, 500.0, 320.0, 240.0, width=640, height=480)
    cam2world = look_at(np.array([0.0, -2.2, 1.4]), BODY_CENTRE)
    bounds = np.stack([body.vertices.min(0), body.vertices.max(0)])
    renderer = SceneRenderer(walls.vertices, walls.faces, None, camera, cam2world, bounds,
                             WIDTH, HEIGHT)
    yield renderer, walls, body, camera, cam2world, bounds
    renderer.close()


def _yellow(body: trimesh.Trimesh, **flags) -> BodyMesh:
    return BodyMesh(np.asarray(body.vertices), np.asarray(body.faces), BASELINE_YELLOW,
                    **flags)


def _is_yellow(pixel: np.ndarray) -> bool:
    r, g, b = (int(c) for c in pixel[:3])
    return r > 120 and g > 80 and b < 0.5 * g


def _projected_centre(camera: Camera, cam2world: np.ndarray) -> tuple[int, int]:
    """The body centre's pixel in the output image (the camera view is scaled by 0.5625,
    and centred horizontally)."""
    world2cam = np.linalg.inv(cam2world)
    p = world2cam[:3, :3] @ BODY_CENTRE + world2cam[:3, 3]
    u, v = camera.fx * p[0] / p[2] + camera.cx, camera.fy * p[1] / p[2] + camera.cy
    s = min(WIDTH / 640, HEIGHT / 480)
    return round(u * s + (WIDTH - 640 * s) / 2), round(v * s)


def test_camera_view_shows_the_body_where_it_projects(room):
    renderer, _, body, camera, cam2world, _ = room
    image = renderer.render("camera", [_yellow(body)])
    assert image.shape == (HEIGHT, WIDTH, 3) and image.dtype == np.uint8
    u, v = _projected_centre(camera, cam2world)
    assert _is_yellow(image[v, u]), image[v, u]
    # Beside the body: the room, lit and not blank.
    assert not _is_yellow(image[v, u + 80]) and image[v, u + 80].std() < 30
    assert 40 < image.mean() < 250 and image.std() > 10


def _plane_depth(corners: np.ndarray, camera: Camera, cam2world: np.ndarray) -> np.ndarray:
    """The camera view's depth (at the camera's own size) of a plane with camera-frame
    ``corners`` (4, 3), drawn from the world frame ``cam2world`` puts it in."""
    world = corners @ cam2world[:3, :3].T + cam2world[:3, 3]
    renderer = SceneRenderer(world, np.array([[0, 2, 1], [0, 3, 2]]), None, camera, cam2world,
                             np.stack([world.min(0), world.max(0)]), camera.width,
                             camera.height)
    try:
        return renderer.depth("camera", [])[0]
    finally:
        renderer.close()


def test_camera_view_draws_each_pixel_as_opencv_centres_it():
    """A pixel (u, v) of the camera view shows the ray through (u, v) as OpenCV (and the
    depth frames' back-projection) read it: pixel centres at whole coordinates, not at
    +0.5 as OpenGL's rasterizer puts them. A plane's straight edge, seen by a tilted,
    rolled, off-centre camera whose axes are not the world's and drawn at the camera's own
    size, lies a quarter of a pixel from two pixel centres, once across the columns and
    once across the rows; each side of it must fall where the OpenCV projection puts it
    (the +0.5 convention puts the first covered pixel one off)."""
    camera = Camera(400.0, 410.0, 171.25, 118.6, width=320, height=240)
    cam2world = look_at(np.array([1.1, -2.3, 1.7]), np.array([0.2, 0.4, 0.9]))
    roll = np.radians(17)
    cam2world[:3, :3] = cam2world[:3, :3] @ np.array(
        [[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    # planes at z = 2 covering x >= x0 (the edge through u = 150.25), then y >= y0 (v = 100.75)
    x0 = (150.25 - camera.cx) / camera.fx * 2.0
    y0 = (100.75 - camera.cy) / camera.fy * 2.0
    columns = _plane_depth(np.array([[x0, -5, 2.0], [x0 + 5, -5, 2], [x0 + 5, 5, 2],
                                     [x0, 5, 2]]), camera, cam2world)
    rows = _plane_depth(np.array([[-5, y0, 2.0], [5, y0, 2], [5, y0 + 5, 2], [-5, y0 + 5, 2]]),
                        camera, cam2world)
    assert np.nonzero(columns[120] > 0)[0].min() == 151  # centre 151 right of the edge
    assert np.nonzero(rows[:, 160] > 0)[0].min() == 101


def test_top_and_side_views_see_through_the_ceiling_and_walls(room):
    renderer, walls, body, _, _, bounds = room
    for view in ("top", "side"):
        image = renderer.render(view, [_yellow(body)])
        centre = image[HEIGHT // 2, WIDTH // 2]
        assert _is_yellow(centre), (view, centre)
        assert (np.array([_is_yellow(p) for p in image.reshape(-1, 3)[::37]]).mean()
                < 0.5), view  # the body, not a close-up of it
    kept = cut_away(walls.vertices, walls.faces, "top", bounds, renderer.views["top"].pose)
    assert walls.vertices[kept].reshape(-1, 3)[:, 2].max() < 2.6  # no ceiling
    assert len(kept) < len(walls.faces)


def test_side_cut_removes_the_wall_in_front_and_keeps_the_one_behind(room):
    renderer, walls, _, _, _, bounds = room
    pose = renderer.views["side"].pose
    towards = pose[:3, 3] - bounds.mean(0)
    towards[2] = 0
    towards /= np.linalg.norm(towards)
    kept = cut_away(walls.vertices, walls.faces, "side", bounds, pose)
    centroids = walls.vertices[kept].mean(1)
    all_centroids = walls.vertices[walls.faces].mean(1)
    # Wall faces, above the floor and below the ceiling cut (0.6 m above the body).
    upright = lambda c: (c[:, 2] > 0.1) & (c[:, 2] < bounds[1, 2] + 0.5)  # noqa: E731
    in_front = lambda c: upright(c) & (c @ towards > 2.0)  # noqa: E731
    behind = lambda c: upright(c) & (c @ towards < -2.0)  # noqa: E731
    assert in_front(all_centroids).sum() > 10 and in_front(centroids).sum() == 0
    assert behind(centroids).sum() == behind(all_centroids).sum() > 10
    assert (centroids[:, 2] < 0.05).sum() == (all_centroids[:, 2] < 0.05).sum()  # the floor


def test_unlit_draws_give_pyrenders_lit_picture(room):
    """The light baked into colours (a light at the camera) draws what pyrender's lit shader
    draws from the same scene: flat walls and a smooth ball, seen by an off-centre camera."""
    import pyrender  # after prox_engine.render, which chooses OpenGL's platform

    renderer, walls, _, _, _, _ = room
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    ball.vertices += BODY_CENTRE + [0.3, 0.0, 0.2]
    baked = renderer.render("camera", [_yellow(ball)])

    def coloured(mesh: trimesh.Trimesh, colour: tuple, smooth: bool) -> "pyrender.Mesh":
        colours = np.tile([*colour, 1.0], (len(mesh.vertices), 1))
        return pyrender.Mesh.from_trimesh(trimesh.Trimesh(mesh.vertices, mesh.faces,
                                                          vertex_colors=colours,
                                                          process=False), smooth=smooth)

    view = renderer.views["camera"]
    pose = view.pose @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV to OpenGL axes
    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 0.0], ambient_light=[AMBIENT] * 3)
    scene.add(coloured(walls, SCENE_COLOUR, smooth=False))
    scene.add(coloured(ball, BASELINE_YELLOW, smooth=True))
    scene.add(pyrender.IntrinsicsCamera(view.fx, view.fy, view.cx, view.cy, znear=0.05,
                                        zfar=100.0), pose=pose)
    scene.add(pyrender.DirectionalLight(intensity=LIGHT_INTENSITY), pose=pose)
    gl = pyrender.OffscreenRenderer(WIDTH, HEIGHT)
    try:
        lit = gl.render(scene)[0]
    finally:
        gl.delete()
    difference = np.abs(lit.astype(int) - baked.astype(int)).max(-1)
    assert lit.std() > 10 and _is_yellow(lit[HEIGHT // 2, WIDTH // 2 + 30])
    assert difference.mean() < 2 and np.percentile(difference, 99) < 10, (
        difference.mean(), np.percentile(difference, 99))


def test_faces_a_view_cannot_show_are_left_out(room):
    """Faces behind the camera, and faces turned away from it, are not drawn; the far wall
    where the camera looks is."""
    renderer, walls, _, _, _, _ = room
    view = renderer.views["camera"]
    vertices, faces = np.asarray(walls.vertices), np.asarray(walls.faces)
    corners = vertices[faces]
    kept = in_view(corners, face_normals(corners), view, WIDTH, HEIGHT, NEAR)
    x, y, z = vertices[faces].mean(1).T
    behind, looked_at = y < -2.4, (y > 2.4) & (np.abs(x) < 0.5) & (np.abs(z - 0.4) < 0.3)
    assert behind.sum() > 10 and not kept[behind].any()
    assert looked_at.sum() > 2 and kept[looked_at].all()
    assert 0 < kept.sum() < len(faces)
    # The same walls wound the other way face out of the room: none is drawn from inside.
    outward = vertices[faces[:, ::-1]]
    assert not in_view(outward, face_normals(outward), view, WIDTH, HEIGHT, NEAR).any()


def test_flagged_vertices_are_painted(room):
    renderer, _, body, camera, cam2world, _ = room
    everything = np.arange(len(body.vertices))
    image = renderer.render("camera", [_yellow(body, penetrating=everything)])
    u, v = _projected_centre(camera, cam2world)
    r, g, b = (int(c) for c in image[v, u])
    assert r > 100 and g < 0.5 * r and b < 0.5 * r, (r, g, b)
    assert PENETRATING_RED[0] > PENETRATING_RED[1]


def test_overlay_draws_the_body_over_the_image(room):
    renderer, _, body, camera, cam2world, _ = room
    blue = np.zeros((480, 640, 3), dtype=np.uint8)
    blue[..., 2] = 200
    image = renderer.overlay(blue, [_yellow(body)])
    u, v = _projected_centre(camera, cam2world)
    assert image[v, u, 0] > 100 and image[v, u, 2] < 120  # mostly the body
    assert tuple(image[v, u + 80]) == (0, 0, 200)  # the photograph, untouched
    assert tuple(image[5, 5]) == (255, 255, 255)  # the margin of a 4:3 image in 16:9
    # soft edges: the body's opacity, read from overlays on a black and a white image,
    # passes through values between none and full along the silhouette
    black, white = (renderer.overlay(np.full((480, 640, 3), level, dtype=np.uint8),
                                     [_yellow(body)]).astype(int) for level in (0, 255))
    opacity = 1 - (white - black).mean(-1) / 255  # 1 in the margins, which are no image
    edge = (opacity > 0.05) & (opacity < 0.75)
    assert edge.sum() > 200 and opacity[opacity < 0.99].max() == pytest.approx(0.8, abs=0.01)


def test_penetrating_vertices_show_through_the_surface_they_penetrate(room):
    """A body sunk 40 cm into a block: its penetrating vertices are hidden by the block
    itself, yet drawn red over it (they used to leave a dozen red pixels at most)."""
    _, walls, _, camera, cam2world, bounds = room
    block = trimesh.creation.box([1.2, 1.2, 0.4])
    block.vertices += [0.0, 0.0, 0.2]
    scene = trimesh.util.concatenate([walls, block])
    body = trimesh.creation.box([0.5, 0.3, 1.8]).subdivide_to_size(0.05)
    body.vertices += BODY_CENTRE
    sunk = np.flatnonzero(body.vertices[:, 2] < 0.4)
    renderer = SceneRenderer(scene.vertices, scene.faces, None, camera, cam2world, bounds,
                             WIDTH, HEIGHT)
    try:
        plain = renderer.render("camera", [_yellow(body)])
        flagged = renderer.render("camera", [_yellow(body, penetrating=sunk)])
    finally:
        renderer.close()

    def red(image: np.ndarray) -> np.ndarray:
        r, g, b = (image[..., i].astype(int) for i in range(3))
        return (r > 150) & (g < 90) & (b < 90)

    assert red(plain).sum() == 0
    assert red(flagged).sum() > 500
    # Above the block the body is visible and not flagged: still yellow.
    u, v = _projected_centre(camera, cam2world)
    assert _is_yellow(flagged[v, u]), flagged[v, u]


def skin_at_torso(data, rec: str) -> list[bool]:
    """Per frame: whether the photograph shows skin where the true torso joints project."""
    from PIL import Image

    from prox_engine.dataset import load_calibration

    camera = load_calibration(data / "calibration" / "Color.json")
    seen = []
    for truth in sorted((data / "ground_truth" / rec).glob("*.npz")):
        joints = np.load(truth)["joints"][[1, 2, 5, 8, 9, 12]]  # neck, shoulders, hips
        uv = np.round(joints[:, :2] / joints[:, 2:] * [camera.fx, camera.fy]
                      + [camera.cx, camera.cy]).astype(int)
        photo = np.asarray(Image.open(data / "recordings" / rec / "Color"
                                      / f"{truth.stem}.jpg").convert("RGB")).astype(int)
        pixels = photo[uv[:, 1], uv[:, 0]]
        r, g, b = pixels.T  # skin: redder than the walls (r - g ~ 3) and the floor (~ 16)
        seen.append(bool(((r > b + 30) & (r > g + 20)).all()))
    return seen


def test_synthetic_photographs_show_the_true_body_where_its_keypoints_are(sitting_data):
    """The demo's colour images are rendered from the ground truth with the calibration's
    camera: skin wherever the true torso joints project (not mirrored, not shifted)."""
    assert skin_at_torso(sitting_data, "Synthetic_00000_01") == [True, True]
