"""Reading the PROX dataset layout.

``BASE/recordings/<rec>/``, ``BASE/keypoints/<rec>/<frame>_keypoints.json``,
``BASE/calibration/Color.json``, ``BASE/cam2world/<Scene>.json``, ``BASE/scenes/<Scene>.ply``,
optional ``BASE/sdf/<Scene>.json`` + ``<Scene>_sdf.npy`` and ``recordings/<rec>/{Color,Depth,
BodyIndex}/<frame>.{jpg,png}``. ``<Scene>`` is the recording name up to its first underscore.
"""
from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera, DepthCamera
from .errors import InputError

KEYPOINT_SUFFIX = "_keypoints.json"
MAX_COORDINATE = 1e4  # metres: a scanned room or its camera is never this far out
KINECT_FPS = 30.0  # PROX's recordings, when frame names carry no time stamps
# PROX frame names: s001_frame_00001__00.00.00.029 (frame number, then h.m.s.ms)
_FRAME_TIME = re.compile(r"frame_(\d+)__(\d+)\.(\d+)\.(\d+)\.(\d+)$")


@dataclass
class Recording:
    """Paths of one recording of a PROX-layout base directory."""

    base: Path
    name: str

    @property
    def scene_name(self) -> str:
        return self.name.split("_", 1)[0]

    @property
    def keypoint_dir(self) -> Path:
        return self.base / "keypoints" / self.name

    @property
    def recording_dir(self) -> Path:
        return self.base / "recordings" / self.name

    @property
    def scene_path(self) -> Path:
        return self.base / "scenes" / f"{self.scene_name}.ply"

    @property
    def cam2world_path(self) -> Path:
        return self.base / "cam2world" / f"{self.scene_name}.json"

    @property
    def calibration_path(self) -> Path:
        return self.base / "calibration" / "Color.json"

    @property
    def sdf_paths(self) -> tuple[Path, Path]:
        return (self.base / "sdf" / f"{self.scene_name}.json",
                self.base / "sdf" / f"{self.scene_name}_sdf.npy")

    def frames(self) -> list[str]:
        """Frame names (keypoint file names without the suffix), sorted."""
        if not self.keypoint_dir.is_dir():
            raise InputError(self.keypoint_dir, "keypoint folder not found")
        return sorted(p.name[: -len(KEYPOINT_SUFFIX)] for p in self.keypoint_dir.iterdir()
                      if p.name.endswith(KEYPOINT_SUFFIX))

    def keypoint_path(self, frame: str) -> Path:
        return self.keypoint_dir / f"{frame}{KEYPOINT_SUFFIX}"

    @property
    def depth_calibration_path(self) -> Path | None:
        """The depth (IR) camera's calibration, ``IR.json`` or ``depth.json``, if any."""
        for name in ("IR.json", "depth.json"):
            if (self.base / "calibration" / name).exists():
                return self.base / "calibration" / name
        return None

    def depth_paths(self, frame: str) -> tuple[Path, Path] | None:
        depth = self.recording_dir / "Depth" / f"{frame}.png"
        mask = self.recording_dir / "BodyIndex" / f"{frame}.png"
        return (depth, mask) if depth.exists() and mask.exists() else None


def _stamps(frames: list[str]) -> list[tuple[int, float]] | None:
    """Frame number and time (s) of each of PROX's frame names
    (``s001_frame_00001__00.00.00.029``), or None when a name has none."""
    matches = [_FRAME_TIME.search(name) for name in frames]
    if not all(matches):
        return None
    return [(int(n), int(h) * 3600 + int(m) * 60 + int(sec) + int(ms) / 1000)
            for n, h, m, sec, ms in (match.groups() for match in matches)]


def frame_times(frames: list[str]) -> list[float]:
    """Each frame's time in the recording (s), from the time stamps in PROX's frame names,
    or their order at 30 frames per second (Kinect) when the names have none."""
    stamps = _stamps(frames)
    if stamps is None:
        return [i / KINECT_FPS for i in range(len(frames))]
    return [time for _, time in stamps]


def frame_rate(frames: list[str]) -> float:
    """Frames per second of a recording: the median over consecutive frames of the frame
    numbers in PROX's frame names over their time stamps; 30 (Kinect) without them."""
    stamps = _stamps(frames) or []
    rates = [(n1 - n0) / (t1 - t0) for (n0, t0), (n1, t1) in zip(stamps, stamps[1:])
             if t1 > t0 and n1 > n0]
    return float(np.median(rates)) if rates else KINECT_FPS


def list_recordings(base: Path) -> list[str]:
    """Recording names: the folders under ``BASE/keypoints``."""
    folder = Path(base) / "keypoints"
    if not folder.is_dir():
        raise InputError(folder, "keypoint folder not found (expected BASE/keypoints/<rec>/)")
    names = sorted(p.name for p in folder.iterdir() if p.is_dir())
    if not names:
        raise InputError(folder, "no recordings (no sub-folders)")
    return names


def _read_json(path: Path, content: bytes | None = None) -> object:
    """The JSON document of ``path`` (or of ``content``, read from it elsewhere)."""
    try:
        return json.loads(Path(path).read_bytes() if content is None else content)
    except FileNotFoundError as exc:
        raise InputError(path, "file not found") from exc
    except RecursionError as exc:
        raise InputError(path, "not valid JSON (nested too deeply)") from exc
    except (OSError, ValueError) as exc:  # ValueError: bad UTF-8 or JSON
        raise InputError(path, f"not valid JSON ({exc})") from exc


def _numbers(path: Path, value: object, name: str, count: int | None = None) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"'{name}' must be a list of numbers") from exc
    if count is not None and array.size != count:
        raise InputError(path, f"'{name}' must have {count} numbers, got {array.size}")
    if not np.isfinite(array).all():
        raise InputError(path, f"'{name}' contains NaN or infinite values")
    return array


def load_calibration(path: Path, content: bytes | None = None) -> Camera:
    """``Color.json`` with ``f`` [fx, fy], ``c`` [cx, cy] and optional ``k`` distortion
    (from ``content`` when given, ``path`` naming it in errors)."""
    data = _read_json(path, content)
    if not isinstance(data, dict) or "f" not in data or "c" not in data:
        raise InputError(path, "calibration needs 'f' [fx, fy] and 'c' [cx, cy]")
    f = _numbers(path, data["f"], "f")
    if f.size == 1:
        f = np.repeat(f, 2)
    if f.size != 2 or (f <= 0).any():
        raise InputError(path, "'f' must be one or two positive focal lengths in pixels")
    c = _numbers(path, data["c"], "c", 2)
    k = _numbers(path, data.get("k", []), "k") if data.get("k") is not None else np.zeros(0)
    if k.size > 5:
        k = k[:5]
    size = data.get("size") or data.get("resolution")
    width = height = None
    if size is not None:
        wh = _numbers(path, size, "size", 2)
        width, height = int(wh[0]), int(wh[1])
    return Camera(float(f[0]), float(f[1]), float(c[0]), float(c[1]), k.tolist(), width, height)


def _view(path: Path, data: dict) -> np.ndarray:
    """A calibration's ``view_mtx`` (3x4: a common frame to the camera's) as 4x4; identity
    when the file has none."""
    view = np.eye(4)
    if data.get("view_mtx") is not None:
        view[:3] = _numbers(path, data["view_mtx"], "view_mtx", 12).reshape(3, 4)
    return view


def load_depth_camera(ir_path: Path, colour_path: Path) -> DepthCamera:
    """PROX's ``IR.json`` (``camera_mtx`` 3x3, ``k``, ``view_mtx`` 3x4) with ``Color.json``'s
    ``view_mtx``: a depth-camera point p goes to the common frame as (p - t) R, then into
    the colour camera's frame by the colour view."""
    data, colour = _read_json(ir_path), _read_json(colour_path)
    if not isinstance(data, dict) or "camera_mtx" not in data:
        raise InputError(ir_path, "depth calibration needs 'camera_mtx' (3x3)")
    if not isinstance(colour, dict):
        raise InputError(colour_path, "calibration must be a JSON object")
    matrix = _numbers(ir_path, data["camera_mtx"], "camera_mtx", 9).reshape(3, 3)
    distortion = (_numbers(ir_path, data["k"], "k") if data.get("k") is not None
                  else np.zeros(0))
    return DepthCamera(matrix, distortion,
                       _view(colour_path, colour) @ np.linalg.inv(_view(ir_path, data)))


def load_cam2world(path: Path, content: bytes | None = None) -> np.ndarray:
    """A 4x4 rigid camera-to-world matrix; rejects non-rigid or singular ones, and
    positions beyond MAX_COORDINATE (from ``content`` when given)."""
    matrix = _numbers(path, _read_json(path, content), "cam2world", 16).reshape(4, 4)
    if (np.abs(matrix[:3, 3]) > MAX_COORDINATE).any():
        raise InputError(path, f"cam2world translation beyond {MAX_COORDINATE:.0f} m")
    rotation = matrix[:3, :3]
    det = np.linalg.det(rotation)
    if abs(det) < 1e-6:
        raise InputError(path, "cam2world is singular")
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-3) or det < 0:
        raise InputError(path, "cam2world rotation is not a proper rotation (orthonormal, det +1)")
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(path, "cam2world last row must be [0, 0, 0, 1]")
    return matrix


@dataclass
class SceneScan:
    """A scene scan as read: vertices (N, 3) float64, triangles (M, 3) int64 and, when
    the file has them, vertex colours (N, 4) RGBA uint8."""

    vertices: np.ndarray
    faces: np.ndarray
    colours: np.ndarray | None = None


def load_scene_mesh(path: Path, content: bytes | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) float64 and triangles (M, 3) int64 of a scene scan (from
    ``content`` when given, ``path`` naming it and its format)."""
    scan = load_scene_scan(path, content)
    return scan.vertices, scan.faces


def load_scene_scan(path: Path, content: bytes | None = None) -> SceneScan:
    """A scene scan with its vertex colours (see :func:`load_scene_mesh`), checked."""
    path = Path(path)
    if content is None and not path.exists():
        raise InputError(path, "scene mesh not found")
    try:
        scan = _read_ply(path, content) if path.suffix.lower() == ".ply" else None
        scan = scan or _read_with_trimesh(path, content)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from exc
    vertices, faces = scan.vertices, scan.faces
    if len(faces) == 0 or len(vertices) == 0:
        raise InputError(path, "mesh has no triangles")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(path, "mesh faces must be triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(path, f"face vertex index out of range ({faces.min()}..{faces.max()} "
                               f"for {len(vertices)} vertices)")
    if not np.isfinite(vertices).all():
        raise InputError(path, "mesh has NaN or infinite vertex coordinates")
    if (np.abs(vertices) > MAX_COORDINATE).any():
        raise InputError(path, f"mesh has coordinates beyond {MAX_COORDINATE:.0f} m (metres "
                               "expected)")
    tri = vertices[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area > 1e-12).any():
        raise InputError(path, "mesh has only degenerate (zero-area) triangles")
    return scan


def _read_ply(path: Path, content: bytes | None) -> SceneScan | None:
    """A PLY as trimesh's reader gives it, without building a mesh (which derives colours
    per face and hashes every array: a 290k-face scan 0.15-0.50 s against 0.02-0.09);
    None where its faces are not all triangles."""
    from trimesh.exchange.ply import load_ply
    from trimesh.visual.color import to_rgba

    with (io.BytesIO(content) if content is not None else path.open("rb")) as stream:
        arrays = load_ply(stream)
    faces = np.asarray(arrays.get("faces", np.zeros((0, 3))))
    if faces.ndim != 2 or faces.shape[1] != 3:
        return None
    vertices = np.asarray(arrays.get("vertices", np.zeros((0, 3))), dtype=np.float64)
    colours = arrays.get("vertex_colors")  # RGB or RGBA: as trimesh's mesh would hold them
    colours = to_rgba(colours) if colours is not None and len(colours) == len(vertices) else None
    return SceneScan(vertices, faces.astype(np.int64), colours)


def _read_with_trimesh(path: Path, content: bytes | None) -> SceneScan:
    """Any format trimesh reads (polygons triangulated), with vertex colours if any."""
    import trimesh

    source = {"file_obj": io.BytesIO(content), "file_type": path.suffix.lstrip(".")} \
        if content is not None else {"file_obj": path}
    mesh = trimesh.load(**source, force="mesh", process=False)
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    visual = getattr(mesh, "visual", None)
    colours = (np.asarray(visual.vertex_colors, dtype=np.uint8)
               if getattr(visual, "kind", None) == "vertex" else None)
    return SceneScan(vertices, np.asarray(getattr(mesh, "faces", np.zeros((0, 3))),
                                          dtype=np.int64), colours)
