"""HTML reports of a fitted recording: ``OUT/<rec>/report/index.html`` with the run, plots
over time, a per-frame table and thumbnails; a page per rendered frame with the camera, top
and side views (and the body over the RGB image when there is one); ``compare.html`` against
a baseline run of the same recording. Static files that open from disk; no external assets.
"""
from __future__ import annotations

import contextlib
import functools
import json
import sys
import time
from urllib.parse import quote
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from . import viewer
from .camera import Camera
from .config import load_config
from .dataset import (Recording, SceneScan, frame_rate, load_calibration, load_cam2world,
                      load_scene_scan)
from .errors import InputError
from .output import atomic_write_text
from .plots import line_chart
from .video import VideoWriter

if TYPE_CHECKING:
    from .render import BodyMesh  # imports OpenGL: loaded only when rendering

SIZE = (960, 540)
THUMB = (320, 180)
VIEW_LABELS = {"overlay": "over the image", "camera": "camera view", "top": "top view",
               "side": "side view"}


def template_dir() -> Path:
    """``templates/`` of the source tree, or where the package installed it."""
    for candidate in (Path(__file__).resolve().parents[1] / "templates",
                      Path(sys.prefix) / "share" / "prox" / "templates"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError("report templates not found (templates/ of the prox sources)")


@dataclass
class FittedRecording:
    """The results of one recording as ``fit_recording`` wrote them (``OUT/<rec>/``)."""

    path: Path
    summary: dict
    _params: dict[str, dict] = field(default_factory=dict, repr=False)

    @classmethod
    def load(cls, path: Path) -> FittedRecording:
        path = Path(path)
        summary_path = path / "summary.json"
        if not summary_path.exists():
            raise InputError(summary_path, "not found: expected the results of one recording "
                                           "(OUT/<rec>/ as written by prox fit)")
        return cls(path, json.loads(summary_path.read_text()))

    @property
    def frames(self) -> list[dict]:
        return self.summary["frames"]

    def params(self, frame: str) -> dict:
        """A frame's ``000.json`` (read once; do not modify)."""
        if frame not in self._params:
            self._params[frame] = json.loads((self.path / "results" / frame / "000.json")
                                             .read_text())
        return self._params[frame]

    def vertices(self, frame: str) -> tuple[np.ndarray, np.ndarray]:
        """The fitted mesh (camera frame): vertices (V, 3) and faces (F, 3)."""
        import trimesh

        mesh = trimesh.load(self.path / "meshes" / frame / "000.ply", process=False)
        return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _world(vertices: np.ndarray, cam2world: np.ndarray) -> np.ndarray:
    return vertices @ cam2world[:3, :3].T + cam2world[:3, 3]


def _colour_image(rec: Recording, frame: str) -> Path | None:
    for suffix in (".jpg", ".png"):
        path = rec.recording_dir / "Color" / f"{frame}{suffix}"
        if path.exists():
            return path
    return None


def _save(image: np.ndarray, path: Path, thumb: Path | None = None) -> None:
    from PIL import Image

    picture = Image.fromarray(image[..., :3])
    picture.save(path, quality=88)
    if thumb is not None:
        picture.resize(THUMB, Image.BILINEAR).save(thumb, quality=85)


@dataclass
class Setting:
    """What every view of a recording's report shares: its camera, the scan (world frame),
    the fit and optional baseline as ``(prefix, run)``, and the box around every body."""

    recording: Recording
    camera: Camera
    cam2world: np.ndarray
    scene: SceneScan
    runs: list[tuple[str, FittedRecording]]
    bounds: np.ndarray  # (2, 3) world-frame corners

    @classmethod
    def load(cls, fit: FittedRecording, data: Path, frames: list[str],
             baseline: FittedRecording | None = None) -> Setting:
        rec = Recording(Path(data), fit.summary["recording"])
        registered = fit.summary.get("registration", {}).get("cam2world")  # as fitted
        cam2world = (np.asarray(registered, dtype=np.float64).reshape(4, 4) if registered
                     else load_cam2world(rec.cam2world_path))
        runs = [("", fit)] + ([("baseline_", baseline)] if baseline else [])
        # One mesh in memory at a time: sequences are long.
        bounds = np.array([[np.inf] * 3, [-np.inf] * 3])
        for _, run in runs:
            for frame in frames:
                points = _world(run.vertices(frame)[0], cam2world)
                bounds = np.stack([np.minimum(bounds[0], points.min(0)),
                                   np.maximum(bounds[1], points.max(0))])
        return cls(rec, load_calibration(rec.calibration_path), cam2world,
                   load_scene_scan(rec.scene_path), runs, bounds)

    @property
    def scene_colours(self) -> np.ndarray | None:
        """The scan's vertex colours (V, 4) in [0, 1], when it has them (PROX scans do)."""
        colours = self.scene.colours
        return None if colours is None else colours.astype(float) / 255

    def body(self, prefix: str, run: FittedRecording, frame: str, flags: bool = True
             ) -> BodyMesh:
        """A fitted body in the world frame, in its run's colour, flagged vertices marked."""
        from .render import BASELINE_YELLOW, FIT_COLOUR, BodyMesh

        flagged = run.params(frame).get("vertices_flagged", {}) if flags else {}
        vertices, faces = run.vertices(frame)
        return BodyMesh(_world(vertices, self.cam2world), faces,
                        BASELINE_YELLOW if prefix else FIT_COLOUR,
                        flagged.get("penetrating"), flagged.get("contact"))


def render_frames(setting: Setting, frames: list[str], out: Path, flags: bool = True,
                  size: tuple[int, int] = SIZE, video: VideoWriter | None = None
                  ) -> dict[str, float]:
    """Write ``out/<frame>_<view>.jpg`` (+ thumbnails, + baseline views), and add the fit's
    views of each frame to ``video``; returns timings."""
    from PIL import Image

    from .render import VIEWS, SceneRenderer

    flip = _mirrored(setting.runs[0][1].summary["config"])
    start = time.perf_counter()
    renderer = SceneRenderer(setting.scene.vertices, setting.scene.faces,
                             setting.scene_colours, setting.camera, setting.cam2world,
                             setting.bounds, *size)
    setup = time.perf_counter() - start
    try:
        start = time.perf_counter()
        for prefix, run in setting.runs:
            for frame in frames:
                body = setting.body(prefix, run, frame, flags)
                thumb = None if prefix else out / f"{frame}_thumb.jpg"
                image_path = _colour_image(setting.recording, frame)
                if image_path is not None:
                    image = Image.open(image_path)
                    image.draft("RGB", size)  # a JPEG decoded at the smallest scale >= size
                    image = image.convert("RGB")
                    if flip:
                        image = image.transpose(Image.FLIP_LEFT_RIGHT)
                    _save(renderer.overlay(np.asarray(image), [body]),
                          out / f"{frame}_{prefix}overlay.jpg", thumb)
                    thumb = None
                images = [renderer.render(view, [body]) for view in VIEWS]
                for view, image in zip(VIEWS, images):
                    _save(image, out / f"{frame}_{prefix}{view}.jpg",
                          thumb if view == "camera" else None)
                if video is not None and not prefix:
                    video.add(images)
        per_frame = (time.perf_counter() - start) / max(1, len(frames) * len(setting.runs))
    finally:
        renderer.close()
    return {"renderer_setup_seconds": setup, "seconds_per_frame": per_frame}


def _mirrored(config_name: str) -> bool:
    """Whether the configuration mirrors the images (Kinect), as the fit did."""
    try:
        return load_config(config_name).flip
    except InputError:  # a user's configuration file that is gone: assume no mirroring
        return False


def build_report(results: Path, data: Path | None = None, baseline: Path | None = None,
                 every: int = 1, flags: bool = True, links: dict[str, str] | None = None,
                 size: tuple[int, int] = SIZE) -> Path:
    """Render and write the report of ``results`` (``OUT/<rec>``); returns its index page.

    ``data`` is the PROX-layout input (default: the path recorded in summary.json),
    ``baseline`` the results of another configuration on the same recording, ``every``
    renders every k-th frame, ``links`` adds download links to the sequence page.
    """
    fit = FittedRecording.load(results)
    base = FittedRecording.load(baseline) if baseline else None
    data = Path(data or fit.summary["data"])
    if not (data / "scenes").is_dir():
        raise InputError(data, "input data not found (the PROX-layout folder that was "
                               "fitted); give it with --data")
    frames = fit.frames
    if base is not None:
        fitted_there = {f["frame"] for f in base.frames}
        frames = [f for f in frames if f["frame"] in fitted_there]
    rendered = frames[::max(1, every)]
    names = [f["frame"] for f in rendered]
    report = fit.path / "report"
    (report / "images").mkdir(parents=True, exist_ok=True)
    (report / "frames").mkdir(exist_ok=True)
    setting = Setting.load(fit, data, names, base)
    fps = frame_rate([f["frame"] for f in frames]) / max(1, every)
    video = len(names) > 1  # a one-frame video shows nothing the frame's page does not
    with (VideoWriter(report / "sequence.mp4", fps) if video
          else contextlib.nullcontext()) as writer:
        timings = render_frames(setting, names, report / "images", flags, size, writer)
    start = time.perf_counter()
    viewer.write_assets(report, setting, names, flags)
    timings["viewer_seconds_per_frame"] = (time.perf_counter() - start) / max(1, len(names))

    env = _templates()
    has_image = {n: (report / "images" / f"{n}_overlay.jpg").exists() for n in names}
    losses = {f["frame"]: fit.params(f["frame"]).get("losses", {}) for f in fit.frames}
    terms = sorted({t for v in losses.values() for t in v})
    rows = [{**f, "losses": losses[f["frame"]], "rendered": f["frame"] in has_image}
            for f in fit.frames]
    row_of = {r["frame"]: r for r in rows}
    common = {"s": fit.summary, "config": fit.summary["config"],
              "colours": _legend_colours(baseline=False), "every": every}
    pages = {"index.html": env.get_template("sequence.html").render(
        **common, frames=rows, rendered=rendered, terms=terms, charts=_charts([fit]),
        links=links or {}, compare=base.summary if base else None, fps=fps, video=video,
        rendered_names=set(names))}
    for i, name in enumerate(names):
        params = dict(fit.params(name))
        flagged = params.pop("vertices_flagged", {})
        params["vertices_flagged"] = {k: f"{len(v)} vertices" for k, v in flagged.items()}
        views = [(v, VIEW_LABELS[v]) for v in ("overlay", "camera", "top", "side")
                 if v != "overlay" or has_image[name]]
        pages[f"frames/{name}.html"] = env.get_template("frame.html").render(
            **common, f=row_of[name], views=views,
            params=json.dumps(params, indent=1), timings=params.get("timings", {})
            .get("stages", {}), previous=names[i - 1] if i else None,
            next=names[i + 1] if i + 1 < len(names) else None)
    pages["viewer.html"] = env.get_template("viewer.html").render(
        **{**common, "colours": _legend_colours(baseline=base is not None)},
        baseline=base.summary["config"] if base else None,
        config_json=viewer.config_json(viewer.page_config(
            rendered, fps, setting.camera, setting.cam2world, setting.bounds,
            base is not None)))
    if base is not None:
        views = [(v, VIEW_LABELS[v]) for v in VIEW_LABELS if v != "overlay"]
        pages["compare.html"] = env.get_template("compare.html").render(
            **{**common, "colours": _legend_colours(baseline=True)}, b=base.summary,
            rows=_comparison(fit.summary, base.summary), charts=_charts([fit, base]),
            rendered=rendered, views=views)
    for name, html in pages.items():
        atomic_write_text(report / name, html)
    atomic_write_text(report / "timings.json", json.dumps(
        {"frames_rendered": len(names), **timings}, indent=1))
    return report / "index.html"


def write_index(out: Path, recordings: list[str], title: str) -> Path:
    """``OUT/index.html``: every recording's numbers, linking to its report."""
    summaries = []
    for name in recordings:
        path = Path(out) / name
        if (path / "summary.json").exists():
            summary = FittedRecording.load(path).summary
            summaries.append({**summary, "has_report": (path / "report" / "index.html")
                              .exists()})
    index = Path(out) / "index.html"
    atomic_write_text(index, _templates().get_template("runs.html").render(
        title=title, summaries=summaries))
    return index


def warm_up() -> None:
    """Import the rendering stack and compile every template, without creating a GL
    context: a worker does it before it forks, so that no job pays for it."""
    from . import render  # noqa: F401  (imports OpenGL, creates no context)

    env = _templates()
    for name in env.list_templates(extensions=["html"]):
        env.get_template(name)


@functools.cache
def _templates():
    """The report pages' Jinja2 environment: one per process, which keeps its compiled
    templates."""
    from jinja2 import Environment, FileSystemLoader, select_autoescape

    env = Environment(loader=FileSystemLoader(template_dir()),
                      autoescape=select_autoescape(["html"]))
    # Names of recordings and frames come from users: quoted whole inside links, and a
    # link that starts with one starts with "./", so that no name reads as a scheme.
    env.filters["urlpart"] = lambda name: quote(str(name), safe="")
    env.globals.update(fmt=_fmt, pct=lambda v: _fmt(v * 100 if v is not None else None,
                                                    "%.1f %%"),
                       cm=lambda v: _fmt(v * 100 if v is not None else None, "%.1f cm"))
    return env


def _fmt(value: float | None, pattern: str) -> str:
    return "-" if value is None or value != value else pattern % value


def _legend_colours(baseline: bool) -> dict[str, str | None]:
    from .render import (BASELINE_YELLOW, CONTACT_BLUE, FIT_COLOUR, PENETRATING_RED)

    rgb = lambda c: ", ".join(str(round(255 * x)) for x in c)  # noqa: E731
    return {"fit": rgb(FIT_COLOUR), "baseline": rgb(BASELINE_YELLOW) if baseline else None,
            "penetrating": rgb(PENETRATING_RED), "contact": rgb(CONTACT_BLUE)}


def _charts(runs: list[FittedRecording]) -> list[str]:
    """Plots over the first run's frames, one line per run."""
    frames = [f["frame"] for f in runs[0].frames]

    def series(value: Callable[[dict], float | None]) -> dict[str, list[float | None]]:
        lines = {}
        for run in runs:
            by_frame = {f["frame"]: f for f in run.frames}
            lines[run.summary["config"]] = [value(by_frame[f]) if f in by_frame else None
                                            for f in frames]
        return lines

    def scaled(key: str, factor: float = 1.0) -> Callable[[dict], float | None]:
        return lambda f: None if f[key] is None else f[key] * factor

    x = list(range(len(frames)))
    return [line_chart("penetrating vertices", x, series(scaled("penetrating_share", 100)),
                       " %"),
            line_chart("max penetration depth", x, series(scaled("max_depth_m", 100)), " cm"),
            line_chart("contact parts touching", x,
                       series(lambda f: len(f["contact_parts"]))),
            line_chart("data error (reprojection)", x, series(scaled("reprojection_error_px")),
                       " px")]


def _comparison(fit: dict, base: dict) -> list[dict]:
    """Rows of the statistics table: baseline, fit, difference (green when better)."""
    def row(label: str, a: float | None, b: float | None, pattern: str,
            lower_is_better: bool = True) -> dict:
        delta = None if a is None or b is None else b - a
        tone = "" if not delta else ("good" if (delta < 0) == lower_is_better else "bad")
        return {"label": label, "baseline": _fmt(a, pattern), "fit": _fmt(b, pattern),
                "delta": "-" if delta is None else ("+" if delta > 0 else "") + pattern % delta,
                "tone": tone}

    pct = lambda s, *k: None if _get(s, *k) is None else _get(s, *k) * 100  # noqa: E731
    return [
        row("penetrating vertices (mean %)", pct(base, "penetration", "mean_penetrating_share"),
            pct(fit, "penetration", "mean_penetrating_share"), "%.2f"),
        row("max penetration depth (cm)", pct(base, "penetration", "max_depth_m"),
            pct(fit, "penetration", "max_depth_m"), "%.1f"),
        row("frames with contact (%)", pct(base, "contact", "share_of_frames_with_contact"),
            pct(fit, "contact", "share_of_frames_with_contact"), "%.0f", lower_is_better=False),
        row("data error (px)", base["reprojection_error_px"], fit["reprojection_error_px"],
            "%.1f"),
        row("seconds per frame", base["seconds_per_frame"], fit["seconds_per_frame"], "%.2f"),
    ]


def _get(d: dict, *keys: str) -> float | None:
    for key in keys:
        d = d.get(key) if isinstance(d, dict) else None
    return d
