"""The report's interactive 3D viewer: ``report/viewer.html``, its script (three.js bundled at
set-up, see ``viewer/``), ``report/3d/scene.glb`` and a GLB per fitted (and baseline) body.

Browsers refuse ``fetch()`` on pages opened from disk, so each GLB has a twin
``<name>.glb.js`` that hands the same bytes to the page; over HTTP the page reads the GLBs.
"""
from __future__ import annotations

import base64
import json
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import glb
from .output import atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    from .camera import Camera
    from .report import Setting

SCRIPT = "viewer.js"


def script_path() -> Path:
    """The bundled viewer script: ``viewer/dist/`` of the source tree (``make setup``
    builds it), or where an installed image put it (``share/prox/``)."""
    for candidate in (Path(__file__).resolve().parents[1] / "viewer" / "dist" / SCRIPT,
                      Path(sys.prefix) / "share" / "prox" / SCRIPT):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError("the 3D viewer's script is not built: run `make setup` (or "
                            "`npm ci && npm run build` in viewer/)")


def write_asset(path: Path, data: bytes) -> None:
    """``path`` (a GLB) and its twin ``path.js`` for pages opened from disk, which hands
    the bytes to the page keyed by its own address."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)
    encoded = base64.b64encode(data).decode()
    atomic_write_text(path.with_name(path.name + ".js"),
                      f'proxGlb(document.currentScript.src, "{encoded}");\n')


def config_json(config: dict) -> str:
    """The page's configuration as JSON that cannot end its <script> element."""
    return (json.dumps(config).replace("<", "\\u003c").replace(">", "\\u003e")
            .replace("&", "\\u0026"))


def write_assets(report: Path, setting: Setting, frames: list[str], flags: bool = True
                 ) -> None:
    """The viewer's script and GLBs under ``report``: ``3d/scene.glb`` (the scan in its
    world frame, simplified), ``3d/<frame>.glb`` per fitted body and
    ``3d/baseline/<frame>.glb`` per baseline body (world frame, flagged vertices in the
    legend's colours); ``setting`` is the report's :class:`report.Setting`."""
    (report / "js").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(script_path(), report / "js" / SCRIPT)
    scene = setting.scene
    write_asset(report / "3d" / "scene.glb", glb.mesh_glb(
        *glb.simplify(scene.vertices, scene.faces, setting.scene_colours)))
    for prefix, run in setting.runs:
        folder = report / "3d" / ("baseline" if prefix else "")
        for frame in frames:
            body = setting.body(prefix, run, frame, flags)
            write_asset(folder / f"{frame}.glb",
                        glb.mesh_glb(body.vertices, body.faces, body.colours()))


def page_config(frames: list[dict], fps: float, camera: Camera, cam2world: np.ndarray,
                bounds: np.ndarray, baseline: bool) -> dict:
    """What viewer.js reads: the frames (with a line of numbers each), the playback rate,
    the recording camera's pose and field of view to start from, the point to orbit about
    (the bodies' centre) and the colours."""
    from .render import BASELINE_YELLOW, FIT_COLOUR, SCENE_COLOUR

    return {
        "frames": [f["frame"] for f in frames],
        "stats": [f"data error {f['reprojection_error_px']:.1f} px · "
                  f"{f['penetrating_share'] * 100:.2f} % of vertices inside the scan · "
                  f"contact: {', '.join(f['contact_parts']) or 'none'}" for f in frames],
        "fps": fps, "baseline": baseline,
        "camera_pose": np.asarray(cam2world).tolist(),
        "fov_y": float(np.degrees(2 * np.arctan((camera.height or 2 * camera.cy) / 2
                                                 / camera.fy))),
        "target": ((bounds[0] + bounds[1]) / 2).tolist(),
        "colours": {"fit": FIT_COLOUR, "baseline": BASELINE_YELLOW, "scene": SCENE_COLOUR},
    }
