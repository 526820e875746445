"""The report's inline SVG charts: valid SVG, gaps for missing values, and short
recordings shown point by point with their values, not as a bare straight line."""
from __future__ import annotations

import xml.etree.ElementTree as ET

from prox_engine.plots import line_chart

SVG = "{http://www.w3.org/2000/svg}"


def _parse(svg: str) -> ET.Element:
    return ET.fromstring(svg)


def test_two_frames_are_two_labelled_points():
    root = _parse(line_chart("data error", [0, 1], {"prox": [4.5, 12.25]}, " px"))
    assert len(root.findall(f"{SVG}circle")) == 2
    texts = [t.text for t in root.findall(f"{SVG}text")]
    assert "4.5 px" in texts and "12.2 px" in texts  # each value, 3 significant digits
    assert texts.count("0") == 1 and texts.count("1") == 1  # every frame on the axis


def test_long_recordings_are_lines_without_markers_and_gaps_break_them():
    x = list(range(100))
    ys = [float(i % 7) for i in x]
    ys[50] = None
    root = _parse(line_chart("contact", x, {"prox": ys, "rgb": [1.0] * 100}))
    lines = root.findall(f"{SVG}polyline")
    assert len(lines) == 3  # prox broken at the gap, rgb whole
    assert not root.findall(f"{SVG}circle")
    assert len(lines[0].get("points").split()) == 50
