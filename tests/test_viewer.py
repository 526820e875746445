"""The report's 3D viewer: its GLB files (the scan simplified, the bodies in the scene's world
frame with their flags) and the page, drawn by headless Chromium over HTTP and from disk."""
from __future__ import annotations

import functools
import json
import re
import subprocess
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from prox_engine import glb
from prox_engine.dataset import load_cam2world
from prox_engine.render import CONTACT_BLUE

from .conftest import REC

BROWSER = ["chromium", "--headless", "--no-sandbox", "--disable-dev-shm-usage",
           "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars",
           "--window-size=1280,1000", "--virtual-time-budget=30000"]


def _load_glb(path: Path) -> trimesh.Trimesh:
    return trimesh.load(path, file_type="glb", force="mesh", process=False)


def _load_glb_bytes(data: bytes) -> trimesh.Trimesh:
    return trimesh.load(trimesh.util.wrap_as_stream(data), file_type="glb", force="mesh",
                        process=False)


def test_simplified_scan_stays_on_the_surface_within_the_face_budget():
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=1.0)  # 81920 faces
    colours = np.tile([0.2, 0.5, 0.8, 1.0], (len(sphere.vertices), 1))
    vertices, faces, paint = glb.simplify(sphere.vertices, sphere.faces, colours,
                                          max_faces=5000)
    assert 1000 < len(faces) <= 5000
    radius = np.linalg.norm(vertices, axis=1)
    assert np.abs(radius - 1).max() < 0.02  # clusters of at most a few cm, on the sphere
    assert faces.max() == len(vertices) - 1  # no unused vertices
    np.testing.assert_allclose(paint, colours[: len(paint)])
    mesh = _load_glb_bytes(glb.mesh_glb(vertices, faces, paint))
    assert len(mesh.faces) == len(faces)
    np.testing.assert_allclose(mesh.visual.vertex_colors[:, :3] / 255, paint[:, :3], atol=0.01)


def test_viewer_bodies_are_the_fits_in_the_world_frame(cli_fits):
    out, _ = cli_fits["prox"]
    report = out / REC / "report"
    scan = _load_glb(report / "3d" / "scene.glb")
    assert 0 < len(scan.faces) <= glb.MAX_SCENE_FACES
    data = out.parent / "data"  # where cli_fits put the input
    cam2world = load_cam2world(data / "cam2world" / f"{REC.split('_')[0]}.json")
    frames = sorted(p.name for p in (out / REC / "meshes").iterdir())
    for frame in frames:
        body = _load_glb(report / "3d" / f"{frame}.glb")
        fitted = trimesh.load(out / REC / "meshes" / frame / "000.ply", process=False)
        world = np.asarray(fitted.vertices) @ cam2world[:3, :3].T + cam2world[:3, 3]
        np.testing.assert_allclose(body.vertices, world, atol=1e-4)
        # the contact vertices carry the legend's blue (red where they also penetrate)
        flags = json.loads((out / REC / "results" / frame / "000.json").read_text()
                           )["vertices_flagged"]
        flagged = sorted(set(flags["contact"]) - set(flags["penetrating"]))
        assert flagged, "the sitting fit touches its chair"
        colours = body.visual.vertex_colors[flagged, :3] / 255
        np.testing.assert_allclose(colours, np.tile(CONTACT_BLUE, (len(flagged), 1)),
                                   atol=0.01)
        assert (report / "3d" / f"{frame}.glb.js").stat().st_size > body.vertices.nbytes / 2


class _Recorder(SimpleHTTPRequestHandler):
    requested: list[str] = []

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the base's name)
        self.requested.append(self.path)


def _drawn_share(screenshot: Path) -> float:
    """Share of the viewer canvas's area (the middle of the page) drawn in something other
    than the page's and the canvas's background greys."""
    picture = np.asarray(Image.open(screenshot).convert("RGB")).astype(int)[250:850, 60:1220]
    background = np.array([[0xf4, 0xf4, 0xf2], [0xfa, 0xfa, 0xfa]])
    distance = np.abs(picture[..., None, :] - background).max(-1).min(-1)
    return float((distance > 24).mean())


def test_viewer_loads_its_glbs_and_draws_in_headless_chromium(cli_fits, tmp_path):
    out, _ = cli_fits["prox"]
    report = out / REC / "report"
    _Recorder.requested = []
    server = ThreadingHTTPServer(("127.0.0.1", 0),
                                 functools.partial(_Recorder, directory=str(report)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_port}/viewer.html"
        for page in (url, (report / "viewer.html").as_uri()):  # over HTTP, then from disk
            dom = subprocess.run([*BROWSER, "--dump-dom", page], capture_output=True,
                                 text=True, timeout=180)
            assert 'data-viewer-ready="1"' in dom.stdout, (page, re.findall(
                r'<body[^>]*>|id="status">[^<]*', dom.stdout), dom.stderr[-1500:])
            screenshot = tmp_path / "viewer.png"
            subprocess.run([*BROWSER, f"--screenshot={screenshot}", page],
                           capture_output=True, timeout=180, check=True)
            drawn = _drawn_share(screenshot)
            print(f"{page}: {drawn:.0%} of the canvas drawn")
            assert drawn > 0.3
    finally:
        server.shutdown()
    frames = sorted(p.name for p in (out / REC / "meshes").iterdir())
    assert "/3d/scene.glb" in _Recorder.requested
    assert f"/3d/{frames[0]}.glb" in _Recorder.requested  # the GLBs themselves, over HTTP
    assert not any(path.endswith(".glb.js") for path in _Recorder.requested)
