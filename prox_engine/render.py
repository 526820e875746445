"""Off-screen renders of fitted bodies in their scene: the recording camera's view, a top and
a side view (ceiling and walls in front of the body cut away), and the body over the RGB image.

pyrender draws through OSMesa (Mesa's llvmpipe, on the CPU) unless ``PYOPENGL_PLATFORM``
says otherwise (``egl`` on GPU nodes). OpenGL reads it when first imported, so this module
sets the default before importing pyrender. Keep one :class:`SceneRenderer` per process and
never fork after rendering (a forked child's render hangs). Every draw is unlit: the shading
of a light at the camera is worked out once per view and vertex (:func:`headlit`), which
makes a draw about a quarter of a lit one's time through llvmpipe.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import pyrender  # noqa: E402  (after the platform is chosen)
import trimesh  # noqa: E402

from .camera import Camera  # noqa: E402

FIT_COLOUR = (0.36, 0.74, 0.56)  # green: apart from the scan, the flags and the baseline
BASELINE_YELLOW = (0.96, 0.76, 0.12)
PENETRATING_RED = (0.90, 0.08, 0.08)
CONTACT_BLUE = (0.10, 0.35, 0.95)
SCENE_COLOUR = (0.66, 0.62, 0.56)
FLAG_OPACITY = 0.85  # flagged vertices over whatever hides them
VIEWS = ("camera", "top", "side")  # the scene views; "overlay" is the camera's over the image
FOV_Y = np.radians(45.0)  # top and side views
NEAR = 0.05  # m: the cameras' near plane
_OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


AMBIENT = 0.3
LIGHT_INTENSITY = 2.0


def headlit(colours: np.ndarray, normals: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Colours (N, 4) in [0, 1] of surface points with unit ``normals`` (N, 3), lit by a
    directional light at a camera looking along ``forward`` plus ambient light, as
    pyrender's lit shader draws vertex-coloured meshes (metallic 0.2, roughness 0.8,
    vertex colours multiplying the light, gamma 2.2), the view direction taken as the
    light's. Drawn unlit, they give the lit picture without its per-pixel cost."""
    x = np.clip(normals @ -np.asarray(forward, dtype=float), 0.001, 1.0)
    f0, c_diff, roughness = 0.232, 0.768, 0.8  # pyrender's mix of dielectric and metal
    k = (roughness + 1) ** 2 / 8
    occlusion = (x / (x * (1 - k) + k)) ** 2
    a2 = roughness ** 4
    facets = a2 / (np.pi * (x * x * (a2 - 1) + 1) ** 2)
    light = AMBIENT + LIGHT_INTENSITY * x * ((1 - f0) * c_diff / np.pi
                                             + f0 * occlusion * facets / (4 * x * x + 0.001))
    lit = np.array(colours, dtype=np.float32)
    lit[:, :3] = np.clip(lit[:, :3] * light[:, None], 0.0, 1.0) ** (1 / 2.2)
    return lit


def _unlit_mesh(positions: np.ndarray, colours: np.ndarray, faces: np.ndarray | None = None
                ) -> pyrender.Mesh:
    """A mesh drawn in its vertex colours (``faces`` None: every 3 positions a triangle)."""
    return pyrender.Mesh([pyrender.Primitive(positions=positions, color_0=colours,
                                             indices=faces)])


@dataclass
class BodyMesh:
    """A body to draw: world-frame vertices, its colour, optional vertices to paint."""

    vertices: np.ndarray  # (V, 3), world frame
    faces: np.ndarray  # (F, 3)
    colour: tuple[float, float, float] = FIT_COLOUR
    penetrating: np.ndarray | None = None  # vertex ids painted red
    contact: np.ndarray | None = None  # vertex ids painted blue

    def colours(self) -> np.ndarray:
        """(V, 4) RGBA in [0, 1]: the body's colour, flagged vertices in the legend's."""
        colours = np.tile(np.array([*self.colour, 1.0]), (len(self.vertices), 1))
        if self.contact is not None:
            colours[np.asarray(self.contact, dtype=int), :3] = CONTACT_BLUE
        if self.penetrating is not None:
            colours[np.asarray(self.penetrating, dtype=int), :3] = PENETRATING_RED
        return colours

    @cached_property
    def _normals(self) -> np.ndarray:
        return trimesh.Trimesh(self.vertices, self.faces, process=False).vertex_normals

    def mesh(self, forward: np.ndarray) -> pyrender.Mesh:
        """The coloured mesh, smooth-shaded for a camera looking along ``forward``."""
        return _unlit_mesh(self.vertices, headlit(self.colours(), self._normals, forward),
                           self.faces)

    @cached_property
    def flag_mesh(self) -> pyrender.Mesh | None:
        """The flagged vertices in their legend colours and the rest black, for the pass
        that shows them through the scene; None when nothing is flagged."""
        flagged = [(ids, colour) for ids, colour in ((self.contact, CONTACT_BLUE),
                                                     (self.penetrating, PENETRATING_RED))
                   if ids is not None and len(ids)]
        if not flagged:
            return None
        colours = np.tile([0.0, 0.0, 0.0, 1.0], (len(self.vertices), 1))
        for ids, colour in flagged:
            colours[np.asarray(ids, dtype=int), :3] = colour
        return _unlit_mesh(self.vertices, colours, self.faces)


@dataclass
class View:
    """A pinhole camera: intrinsics in output pixels, the principal point measured from the
    image's edge as OpenGL rasterizes (pixel centres at +0.5; see :func:`camera_view`), and
    an OpenCV camera-to-world pose."""

    fx: float
    fy: float
    cx: float
    cy: float
    pose: np.ndarray


def camera_view(camera: Camera, cam2world: np.ndarray, width: int, height: int) -> View:
    """The recording camera, scaled to the output size (centred when the aspect differs).
    Its principal point is given from the image's edge, as OpenGL rasterizes (a pixel's
    centre half a pixel in), where OpenCV's intrinsics put pixel centres at whole
    coordinates: drawn at (cx, cy), a rendered depth frame was read half a pixel off."""
    image_w = camera.width or 2 * camera.cx
    image_h = camera.height or 2 * camera.cy
    s = min(width / image_w, height / image_h)
    return View(camera.fx * s, camera.fy * s, (camera.cx + 0.5) * s + (width - image_w * s) / 2,
                (camera.cy + 0.5) * s + (height - image_h * s) / 2,
                np.asarray(cam2world, dtype=float))


def _looking(centre: np.ndarray, forward: np.ndarray, right: np.ndarray, distance: float
             ) -> np.ndarray:
    """OpenCV camera-to-world pose looking along ``forward`` at ``centre`` from ``distance``,
    with ``right`` (perpendicular to ``forward``) as the image's x axis."""
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(forward, right), forward], 1)
    pose[:3, 3] = centre - forward * distance
    return pose


def _horizontal(v: np.ndarray) -> np.ndarray:
    v = np.array([v[0], v[1], 0.0])
    return v / max(np.linalg.norm(v), 1e-9)


def overview_views(bounds: np.ndarray, cam2world: np.ndarray, width: int, height: int,
                   margin: float = 0.2, side_tilt: float = np.radians(15.0)
                   ) -> dict[str, View]:
    """Top and side cameras framing the bodies' world box ``bounds`` (2, 3), oriented like
    the recording camera: the top view has the camera at the bottom of the image, the side
    view looks across the camera's line of sight (where depth errors show), tilted down."""
    forward = _horizontal(cam2world[:3, 2])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    centre = bounds.mean(0)
    half = (bounds[1] - bounds[0]) / 2
    f = height / 2 / np.tan(FOV_Y / 2)
    # Distance at which a radius fills half the image height, from the box's near face.
    distance = lambda radius, depth: radius * f / (height / 2) + depth  # noqa: E731

    top_radius = max(half[0], half[1]) + margin
    top = _looking(centre, np.array([0.0, 0.0, -1.0]), right, distance(top_radius, half[2]))
    side_forward = -right * np.cos(side_tilt) - np.array([0.0, 0.0, np.sin(side_tilt)])
    side_radius = max(half[2], abs(half @ forward)) + margin
    side = _looking(centre, side_forward, forward,
                    distance(side_radius, np.abs(half[:2]) @ np.abs(right[:2])))
    return {name: View(f, f, width / 2, height / 2, pose)
            for name, pose in (("top", top), ("side", side))}


def cut_away(vertices: np.ndarray, faces: np.ndarray, view: str, bounds: np.ndarray,
             pose: np.ndarray) -> np.ndarray:
    """Faces kept for a top or side view: no ceiling above the bodies, and (side view) nothing
    between the camera and the bodies."""
    centroids = vertices[faces].mean(1)
    keep = centroids[:, 2] < bounds[1, 2] + (0.3 if view == "top" else 0.6)
    if view == "side":
        towards = _horizontal(pose[:3, 3] - bounds.mean(0))
        corners = np.array(np.meshgrid(*bounds.T)).reshape(3, -1).T
        in_front = centroids @ towards > (corners @ towards).max() + 0.15
        keep &= ~in_front | (centroids[:, 2] < bounds[0, 2] + 0.05)  # keep the floor
    return faces[keep]


def face_normals(corners: np.ndarray) -> np.ndarray:
    """Normals (F, 3), not unit, of triangles ``corners`` (F, 3, 3), by their winding."""
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def in_view(corners: np.ndarray, normals: np.ndarray, view: View, width: int, height: int,
            near: float) -> np.ndarray:
    """Which faces (F,), world-frame ``corners`` (F, 3, 3) with :func:`face_normals`, a
    draw from ``view`` can show: those facing its camera (OpenGL culls the others) and not
    wholly beyond one side of its frustum. Left out before drawing, they cost neither
    upload nor shading."""
    facing = np.einsum("ij,ij->i", normals, view.pose[:3, 3] - corners[:, 0]) >= 0
    local = (corners - view.pose[:3, 3]) @ view.pose[:3, :3]  # camera frame (OpenCV)
    x, y, z = local[..., 0], local[..., 1], local[..., 2]
    outside = ((z < near).all(1) | (x < -view.cx / view.fx * z).all(1)
               | (x > (width - view.cx) / view.fx * z).all(1)
               | (y < -view.cy / view.fy * z).all(1)
               | (y > (height - view.cy) / view.fy * z).all(1))
    return facing & ~outside


class SceneRenderer:
    """Renders one recording's scene with bodies in it, from the camera, the top and the side.

    The scene meshes (whole for the camera view, cut for the others) are uploaded once and
    kept; only the bodies change between frames.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None,
                 camera: Camera, cam2world: np.ndarray, bounds: np.ndarray,
                 width: int = 960, height: int = 540) -> None:
        self.width, self.height = width, height
        self.views = {"camera": camera_view(camera, cam2world, width, height),
                      **overview_views(bounds, cam2world, width, height)}
        self.scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 0.0])
        colours = (np.tile([*SCENE_COLOUR, 1.0], (len(vertices), 1)) if colours is None
                   else np.asarray(colours, dtype=float))
        self.scene_nodes = {}
        for name, view in self.views.items():
            kept = faces if name == "camera" else cut_away(vertices, faces, name, bounds,
                                                           view.pose)
            corners = vertices[kept]  # (F, 3, 3): flat-shaded, each face its own vertices
            normals = face_normals(corners)
            shown = in_view(corners, normals, view, width, height, NEAR)
            kept, corners, normals = kept[shown], corners[shown], normals[shown]
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            lit = headlit(colours[kept].reshape(-1, 4), np.repeat(normals, 3, axis=0),
                          view.pose[:3, 2])
            self.scene_nodes[name] = self.scene.add(_unlit_mesh(corners.reshape(-1, 3), lit))
        self.camera_node = self.scene.add(pyrender.IntrinsicsCamera(1, 1, 0, 0, znear=NEAR,
                                                                    zfar=100.0))
        self.renderer = pyrender.OffscreenRenderer(width, height)

    def render(self, view: str, bodies: list[BodyMesh]) -> np.ndarray:
        """An RGB image (H, W, 3) uint8 of the bodies in the scene from ``view``, their
        flagged vertices shown through the scene (penetrating ones are inside it, hidden
        by the very surfaces they penetrate)."""
        colour = self._draw(view, self._meshes(view, bodies), with_scene=True)[0]
        flagged = [b.flag_mesh for b in bodies if b.flag_mesh is not None]
        if not flagged:
            return colour
        # Without the scene: the flags' exact legend colours wherever they project.
        flat, depth = self._draw(view, flagged, with_scene=False)
        drawn = depth > 0
        pixels = flat[drawn].astype(np.int16)
        blended = colour[drawn].astype(float)
        for legend in (CONTACT_BLUE, PENETRATING_RED):
            target = np.array(legend) * 255
            mask = np.abs(pixels - target).max(-1) < 60
            blended[mask] = (1 - FLAG_OPACITY) * blended[mask] + FLAG_OPACITY * target
        out = colour.copy()
        out[drawn] = blended.round().astype(np.uint8)
        return out

    def depth(self, view: str, bodies: list[BodyMesh]) -> tuple[np.ndarray, np.ndarray]:
        """Depth along the view's axis (H, W; 0 where nothing is) of the scene with the
        bodies in it, and of the bodies alone."""
        meshes = self._meshes(view, bodies)
        return (self._draw(view, meshes, with_scene=True)[1],
                self._draw(view, meshes, with_scene=False)[1])

    def _meshes(self, view: str, bodies: list[BodyMesh]) -> list[pyrender.Mesh]:
        forward = self.views[view].pose[:3, 2]
        return [b.mesh(forward) for b in bodies]

    def _draw(self, view: str, meshes: list[pyrender.Mesh], with_scene: bool
              ) -> tuple[np.ndarray, np.ndarray]:
        """Colour (H, W, 3) and depth (H, W; 0 where nothing was drawn), unlit."""
        v = self.views[view]
        self.camera_node.camera.fx, self.camera_node.camera.fy = v.fx, v.fy
        self.camera_node.camera.cx, self.camera_node.camera.cy = v.cx, v.cy
        self.scene.set_pose(self.camera_node, v.pose @ _OPENGL_FROM_OPENCV)
        for name, node in self.scene_nodes.items():
            node.mesh.is_visible = with_scene and name == view
        nodes = [self.scene.add(mesh) for mesh in meshes]
        try:
            # OSMesa has no alpha channel: the depth buffer tells what was drawn.
            colour, depth = self.renderer.render(self.scene, flags=pyrender.RenderFlags.FLAT)
        finally:
            for node in nodes:
                self.scene.remove_node(node)
        return colour, depth

    def overlay(self, image: np.ndarray, bodies: list[BodyMesh], alpha: float = 0.8
                ) -> np.ndarray:
        """The bodies drawn over the RGB ``image`` as the camera saw them (H, W, 3) uint8."""
        from PIL import Image, ImageFilter

        h, w = image.shape[:2]
        canvas = np.full((self.height, self.width, 3), 255, dtype=np.uint8)
        scale = min(self.width / w, self.height / h)
        resized = np.asarray(Image.fromarray(image[..., :3]).resize(
            (round(w * scale), round(h * scale)), Image.BILINEAR))
        top, left = (self.height - resized.shape[0]) // 2, (self.width - resized.shape[1]) // 2
        canvas[top:top + resized.shape[0], left:left + resized.shape[1]] = resized
        colour, depth = self._draw("camera", self._meshes("camera", bodies), with_scene=False)
        # soft edges: the body's mask blurred by about a pixel
        mask = Image.fromarray(((depth > 0) * 255).astype(np.uint8)).filter(
            ImageFilter.GaussianBlur(1.0))
        opacity = np.asarray(mask)
        rows, cols = np.flatnonzero(opacity.any(1)), np.flatnonzero(opacity.any(0))
        if len(rows):  # blended only in the box around the body
            box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            a = opacity[box][..., None].astype(np.float32) * (alpha / 255)
            canvas[box] = (canvas[box] * (1 - a) + colour[box] * a).astype(np.uint8)
        return canvas

    def close(self) -> None:
        self.renderer.delete()
