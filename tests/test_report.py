"""HTML reports: written by `prox fit`, rebuilt with a comparison by `prox report`, valid
(HTML Tidy), every link and image resolving, and loading in headless Chromium."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
from PIL import Image

from prox_engine.errors import InputError
from prox_engine.report import build_report

from .conftest import REC


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.links += [value for name, value in attrs if name in ("href", "src") and value]


def _check_page(page: Path) -> list[Path]:
    """Tidy finds nothing to say; every relative link resolves. Returns the images."""
    tidy = subprocess.run(["tidy", "-q", "-e", str(page)], capture_output=True, text=True)
    assert tidy.returncode == 0, f"{page}: {tidy.stderr}"
    parser = _Links()
    parser.feed(page.read_text())
    images = []
    for link in parser.links:
        assert not link.startswith(("http:", "https:", "//")), f"{page}: external {link}"
        target = (page.parent / unquote(link.split("#")[0])).resolve()
        assert target.exists(), f"{page}: {link} does not resolve"
        if target.suffix == ".jpg":
            images.append(target)
    return images


def _pages(report: Path) -> list[Path]:
    return [report / "index.html", report / "viewer.html",
            *sorted((report / "frames").glob("*.html"))]


def test_fit_writes_a_report_whose_links_and_images_resolve(cli_fits):
    out, run = cli_fits["prox"]
    report = out / REC / "report"
    assert "reports:" in run.stdout
    images = [i for page in [*_pages(report), out / "index.html"] for i in _check_page(page)]
    views = {i.stem.rsplit("_", 1)[1] for i in images}
    assert {"thumb", "overlay", "camera", "top", "side"} <= views
    for path in images:
        picture = np.asarray(Image.open(path))
        assert picture.shape in ((540, 960, 3), (180, 320, 3)), path
        assert picture.std() > 10, f"{path} is blank"
    index = (report / "index.html").read_text()
    assert "<svg" in index and "penetrating vertices" in index  # the plots
    assert "../meshes/" in index and "../results/" in index  # the downloads


def test_report_command_adds_the_comparison(cli_fits, tmp_path):
    prox, _ = cli_fits["prox"]
    rgb, _ = cli_fits["rgb"]
    results = tmp_path / REC
    shutil.copytree(prox / REC, results)
    run = subprocess.run([sys.executable, "-m", "prox_engine.cli", "report", str(results),
                          "--compare", str(rgb / REC)], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert re.search(r"2 frames rendered, [\d.]+ s per frame", run.stdout), run.stdout
    compare = results / "report" / "compare.html"
    images = _check_page(compare)
    assert any("_baseline_" in i.name for i in images) and any(
        "_baseline_" not in i.name for i in images)
    text = compare.read_text()
    assert "prox against rgb" in text and "penetrating vertices (mean %)" in text
    assert 'href="compare.html"' in (results / "report" / "index.html").read_text()


def test_a_report_of_one_rendered_frame_has_no_video(cli_fits, tmp_path):
    prox, _ = cli_fits["prox"]
    results = tmp_path / REC
    shutil.copytree(prox / REC, results, ignore=shutil.ignore_patterns("report"))
    index = build_report(results, every=2)  # renders the first of the two frames
    assert not (results / "report" / "sequence.mp4").exists()
    assert "<video" not in index.read_text() and _check_page(index)


def test_report_names_the_missing_input(cli_fits, tmp_path):
    prox, _ = cli_fits["prox"]
    with pytest.raises(InputError, match="--data"):
        build_report(prox / REC, data=tmp_path / "nowhere")


def test_report_loads_in_headless_chromium(cli_fits, tmp_path):
    out, _ = cli_fits["prox"]
    page = out / REC / "report" / "index.html"
    browser = ["chromium", "--headless", "--no-sandbox", "--disable-gpu",
               "--disable-dev-shm-usage", "--hide-scrollbars", "--virtual-time-budget=5000"]
    dom = subprocess.run([*browser, "--dump-dom", page.as_uri()], capture_output=True,
                         text=True, timeout=120)
    loaded = re.search(r'data-images-loaded="(\d+)/(\d+)"', dom.stdout)
    assert loaded, dom.stderr[-2000:]
    assert int(loaded[1]) == int(loaded[2]) > 0, loaded[0]
    screenshot = tmp_path / "report.png"
    subprocess.run([*browser, "--window-size=1280,1400", f"--screenshot={screenshot}",
                    page.as_uri()], capture_output=True, timeout=120, check=True)
    picture = np.asarray(Image.open(screenshot).convert("RGB"))
    assert picture.shape == (1400, 1280, 3) and picture.std() > 20
    print(f"report screenshot: {screenshot}")


def test_sequence_video_has_a_frame_per_rendered_frame_and_plays_in_chromium(cli_fits,
                                                                            tmp_path):
    import imageio_ffmpeg

    out, _ = cli_fits["prox"]
    report = out / REC / "report"
    frames = json.loads((out / REC / "summary.json").read_text())["frames"]
    count, seconds = imageio_ffmpeg.count_frames_and_secs(str(report / "sequence.mp4"))
    # the synthetic recording's frame names are 1 s apart: 1 frame per second
    assert count == len(frames) == 2 and seconds == pytest.approx(2.0, abs=0.05)
    assert 'src="sequence.mp4"' in (report / "index.html").read_text()
    probe = tmp_path / "probe.html"  # a page that reports what the <video> element reached
    probe.write_text(
        '<!DOCTYPE html><html><body><video id="v" muted preload="auto" src="'
        + (report / "sequence.mp4").as_uri() + '"></video><script>'
        'var v = document.getElementById("v");'
        'v.addEventListener("loadeddata", function () {'
        '  document.body.setAttribute("data-video", v.readyState + " " + v.duration); });'
        'v.addEventListener("error", function () {'
        '  document.body.setAttribute("data-video", "error " + v.error.code); });'
        '</script></body></html>')
    dom = subprocess.run(["chromium", "--headless", "--no-sandbox", "--disable-gpu",
                          "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=120)
    state = re.search(r'data-video="([^"]*)"', dom.stdout)
    assert state, dom.stderr[-2000:]
    ready, duration = state[1].split()
    assert int(ready) >= 2 and float(duration) == pytest.approx(2.0, abs=0.05), state[1]


HOSTILE = "javascript:alert(document.domain)"


def test_names_from_uploads_never_become_a_link_scheme():
    """A frame or recording named like a URL (upload names are untrusted) is linked as a
    relative path ("./" and quoted), and shown escaped."""
    from prox_engine.report import _legend_colours, _templates

    frame = {"frame": "s001", "reprojection_error_px": 1.0, "penetrating_share": 0.0,
             "max_depth_m": 0.0, "contact_parts": [], "seconds": 1.0, "losses": {}}
    page = _templates().get_template("frame.html").render(
        f=frame, s={"recording": "<b>r</b>", "config": "prox"}, views=[], timings={},
        params="", previous=HOSTILE, next=f"{HOSTILE}<x>",
        colours=_legend_colours(baseline=False))
    hrefs = _Links()
    hrefs.feed(page)
    assert "./javascript%3Aalert%28document.domain%29.html" in hrefs.links
    assert "./javascript%3Aalert%28document.domain%29%3Cx%3E.html" in hrefs.links
    assert not any(link.lower().startswith("javascript") for link in hrefs.links)
    assert "<b>r</b>" not in page and "&lt;x&gt;" in page
    runs = _templates().get_template("runs.html").render(
        title="t", summaries=[{"recording": HOSTILE, "config": "prox", "has_report": True,
                               "seconds_per_frame": 1.0, "reprojection_error_px": 1.0,
                               "penetration": {"mean_penetrating_share": 0.0},
                               "contact": {"share_of_frames_with_contact": 1.0}}])
    hrefs = _Links()
    hrefs.feed(runs)
    assert "./javascript%3Aalert%28document.domain%29/report/index.html" in hrefs.links


def test_pages_agree_on_penetration_and_label_the_losses(cli_fits):
    """The index, the sequence page and the frame page state the same penetration share
    (to 0.01 %: the sequence page said 0.0 % where the index said 0.04), the per-frame
    loss columns say that they are losses, and the pages give the person's height."""
    out, _ = cli_fits["prox"]
    report = out / REC / "report"
    index = (out / "index.html").read_text()
    sequence = (report / "index.html").read_text()
    [frame] = sorted((report / "frames").glob("*.html"))[:1]
    summary = json.loads((out / REC / "summary.json").read_text())
    share = f"{summary['penetration']['mean_penetrating_share'] * 100:.2f}"
    assert f"<td>{share}</td>" in index
    assert f"<dd>{share} % of vertices on average" in sequence
    assert re.search(r"<dd>\d+\.\d\d % of vertices, max depth", frame.read_text())
    assert f"<dd>{summary['stature_m']:.2f} m standing, from the fitted shape" in sequence
    assert re.search(r"<dd>1\.\d\d m standing, from the fitted shape</dd>", frame.read_text())
    assert "<th>loss: data</th>" in sequence
