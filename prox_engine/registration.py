"""Re-registering the scan to the camera from the depth frames' scene pixels.

A scan's ``cam2world`` is typically a degree and a centimetre or two off. At 3 m a degree
moves the floor under a person's feet by 5 cm, and a body the scene terms stand on that
floor by 10-15 cm in depth. When a recording has depth frames, the pixels off the body see
the room: point-to-plane ICP of those points against the scan (robust weights for clutter
the scan lacks, damping that leaves directions the room does not constrain where they
were) corrects the registration, and it is kept only if it is small and fits better.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .camera import Camera, DepthCamera
from .dataset import Recording, load_depth_camera
from .depth import load_depth_points
from .errors import InputError

FRAMES = 3  # depth frames, spread over the recording (the person stands elsewhere in each)
POINTS_PER_FRAME = 4000
ITERATIONS = 30
GATE_M = (0.20, 0.02)  # points farther off their face's plane get no weight; the gate
# narrows over the first half of the steps, from beyond a degree at 5 m
ON_SCAN_M = 0.02  # after: a point this far off the scan is clutter the scan lacks
DAMPING = 1e-3  # relative to the mean curvature: unconstrained directions stay put
MAX_ROTATION_DEG = 5.0  # a larger correction means the room was not recognised
MAX_SHIFT_M = 0.20
MIN_INLIERS = 0.5  # share of the points within ON_SCAN_M of the scan after the correction
OFF, NO_DEPTH = "off", "no depth frames"  # reasons for not trying, unlike failing


@dataclass
class Registration:
    """The scan-to-camera registration used, and how it was corrected."""
    cam2world: np.ndarray
    refined: bool
    reason: str = ""  # why not, when not refined
    rotation_deg: float = 0.0
    shift_m: float = 0.0
    inliers: float = 0.0
    residual_before_m: float = 0.0
    residual_after_m: float = 0.0

    @property
    def failed(self) -> bool:
        """Whether a refinement was tried and not kept (worth a warning)."""
        return not self.refined and self.reason not in (OFF, NO_DEPTH)

    def summary(self) -> dict:
        return {"refined": self.refined, "reason": self.reason, "failed": self.failed,
                "rotation_deg": round(self.rotation_deg, 3), "shift_m": round(self.shift_m, 4),
                "inliers": round(self.inliers, 3),
                "residual_before_m": round(self.residual_before_m, 4),
                "residual_after_m": round(self.residual_after_m, 4),
                "cam2world": np.round(self.cam2world, 6).tolist()}


@dataclass
class _Surface:
    """The scan's faces as centres (a k-d tree), unit normals, and the distance within
    which a point on a face has that face's centre (the 90th percentile of the faces'
    centre-to-corner distances: a scanner's faces are small and even)."""
    tree: cKDTree
    centres: np.ndarray
    normals: np.ndarray
    radius: float

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray) -> _Surface:
        triangles = np.asarray(vertices, np.float64)[np.asarray(faces)]
        normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        length = np.linalg.norm(normals, axis=1)
        keep = length > 1e-12
        triangles = triangles[keep]
        centres = triangles.mean(1)
        radius = float(np.percentile(np.linalg.norm(triangles - centres[:, None], axis=2), 90))
        return cls(cKDTree(centres), centres, normals[keep] / length[keep, None], radius)

    def residuals(self, points: np.ndarray, gate: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point-to-plane residuals of ``points`` (world) to their nearest faces, for the
        points within ``gate`` of a face: (residuals, normals, index of the points)."""
        distance, index = self.tree.query(points, distance_upper_bound=gate + self.radius)
        paired = np.flatnonzero(np.isfinite(distance))
        n = self.normals[index[paired]]
        r = ((points[paired] - self.centres[index[paired]]) * n).sum(1)
        near = np.abs(r) < gate
        return r[near], n[near], paired[near]


def refine_registration(vertices: np.ndarray, faces: np.ndarray, cam2world: np.ndarray,
                        points_cam: np.ndarray) -> Registration:
    """Correct ``cam2world`` (4, 4) so that the depth frames' scene points ``points_cam``
    (N, 3, colour-camera frame) lie on the scan (``vertices``, ``faces``, world frame)."""
    surface = _Surface.of(vertices, faces)
    points_cam = np.asarray(points_cam, np.float64)
    given = np.asarray(cam2world, np.float64)
    current = given.copy()
    for step in range(ITERATIONS):
        gate = GATE_M[0] + (GATE_M[1] - GATE_M[0]) * min(1.0, step / (ITERATIONS / 2))
        world = points_cam @ current[:3, :3].T + current[:3, 3]
        r, n, paired = surface.residuals(world, gate)
        if len(r) < 6:
            return Registration(given, False, reason="the depth frames do not see the scan")
        weight = (1 - (r / gate) ** 2) ** 2  # Tukey's biweight
        centre = world[paired].mean(0)
        # r(x) ~ r + n . (w x (p - c) + t) for a small rotation w about c and a shift t
        jacobian = np.concatenate([np.cross(world[paired] - centre, n), n], 1)
        hessian = jacobian.T @ (weight[:, None] * jacobian)
        hessian += DAMPING * np.trace(hessian) / 6 * np.eye(6)
        x = -np.linalg.solve(hessian, jacobian.T @ (weight * r))
        update = np.eye(4)
        update[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
        update[:3, 3] = centre - update[:3, :3] @ centre + x[3:]
        current = update @ current
        if np.linalg.norm(x) < 1e-6:
            break
    return _judge(surface, points_cam, given, current)


def _judge(surface: _Surface, points_cam: np.ndarray, given: np.ndarray,
           refined: np.ndarray) -> Registration:
    """Keep ``refined`` if it is a small correction that fits the points better."""
    def fit(cam2world: np.ndarray) -> tuple[float, float]:
        world = points_cam @ cam2world[:3, :3].T + cam2world[:3, 3]
        r, _, _ = surface.residuals(world, ON_SCAN_M)
        return float(np.sqrt((r ** 2).mean())) if len(r) else np.inf, len(r) / len(points_cam)
    (before, _), (after, inliers) = fit(given), fit(refined)
    change = refined @ np.linalg.inv(given)
    rotation = float(np.degrees(Rotation.from_matrix(change[:3, :3]).magnitude()))
    # the shift of the camera centre, the point whose placement the fit depends on
    shift = float(np.linalg.norm(refined[:3, 3] - given[:3, 3]))
    figures = dict(rotation_deg=rotation, shift_m=shift, inliers=inliers,
                   residual_before_m=before, residual_after_m=after)
    if rotation > MAX_ROTATION_DEG or shift > MAX_SHIFT_M:
        return Registration(given, False, reason="correction too large to trust", **figures)
    if inliers < MIN_INLIERS:
        return Registration(given, False, reason="too few depth points on the scan", **figures)
    if not after < before:
        return Registration(given, False, reason="no better than the given registration",
                            **figures)
    return Registration(refined, True, **figures)


def register_scan(rec: Recording, frames: list[str], cam2world: np.ndarray,
                  vertices: np.ndarray, faces: np.ndarray, camera: Camera,
                  depth_camera: DepthCamera | None, flip: bool) -> Registration:
    """``cam2world`` refined from the scene pixels of up to FRAMES of the recording's depth
    frames (as given when it has none, or none can be read), seen through ``depth_camera``
    (default: the recording's own calibration, if any; only this step needs it then, so
    an unreadable one leaves the registration as given)."""
    if depth_camera is None and rec.depth_calibration_path:
        try:
            depth_camera = load_depth_camera(rec.depth_calibration_path, rec.calibration_path)
        except InputError as exc:
            return Registration(cam2world, False, f"unreadable depth calibration ({exc})")
    picked = frames[::max(1, -(-len(frames) // FRAMES))]
    points, unreadable = [], 0
    for name in picked:
        paths = rec.depth_paths(name)
        if paths is None:
            continue
        try:
            points.append(load_depth_points(*paths, camera, flip, POINTS_PER_FRAME,
                                            depth_camera=depth_camera, body=False).numpy())
        except InputError:
            unreadable += 1
    if not points:
        return Registration(cam2world, False, reason="unreadable depth frames" if unreadable
                            else NO_DEPTH)
    return refine_registration(vertices, faces, cam2world, np.concatenate(points))
