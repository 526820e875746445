"""Small inline SVG line charts for the reports (no JavaScript, no external assets)."""
from __future__ import annotations

import math
from html import escape

PALETTE = ("#2e9e6b", "#e0a800", "#1f5fd6")  # the fit's green, the baseline's yellow
DOTS = 30  # with this many points or fewer, each is marked
LABELS = 5  # and with this many or fewer, each also carries its value


def _ticks(low: float, high: float, count: int = 4) -> list[float]:
    if high <= low:
        high = low + 1.0
    step = 10 ** math.floor(math.log10((high - low) / count))
    for factor in (1, 2, 5, 10):
        if (high - low) / (step * factor) <= count:
            step *= factor
            break
    start = math.floor(low / step) * step
    return [start + i * step for i in range(int((high - start) / step) + 2)
            if start + i * step <= high + step * 0.999]


def line_chart(title: str, x: list[float], series: dict[str, list[float | None]],
               unit: str = "", width: int = 460, height: int = 170) -> str:
    """An SVG chart of one or more series over ``x`` (None leaves a gap)."""
    left, right, top, bottom = 46, 10, 22, 24
    values = [v for ys in series.values() for v in ys if v is not None and math.isfinite(v)]
    lo = min([0.0, *values])
    ticks = _ticks(lo, max(values, default=1.0))
    hi = ticks[-1]
    x0, x1 = (min(x), max(x)) if x else (0, 1)
    def sx(v: float) -> float:
        return left + (v - x0) / ((x1 - x0) or 1) * (width - left - right)

    def sy(v: float) -> float:
        return height - bottom - (v - lo) / ((hi - lo) or 1) * (height - top - bottom)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" class="chart" width="{width}" '
             f'height="{height}" viewBox="0 0 {width} {height}" role="img" '
             f'aria-label="{escape(title)}">',
             f'<text x="{left}" y="14" class="chart-title">{escape(title)}</text>']
    for t in ticks:
        parts.append(f'<line x1="{left}" x2="{width - right}" y1="{sy(t):.1f}" '
                     f'y2="{sy(t):.1f}" class="grid"/>'
                     f'<text x="{left - 4}" y="{sy(t) + 4:.1f}" class="tick" '
                     f'text-anchor="end">{t:g}{escape(unit)}</text>')
    frame_ticks = x if len(x) <= 10 else [x0, x1]
    parts.append(f'<text x="{left - 4}" y="{height - 6}" class="tick" '
                 f'text-anchor="end">frame</text>')
    parts += [f'<text x="{sx(xi):.1f}" y="{height - 6}" class="tick" '
              f'text-anchor="middle">{xi:g}</text>' for xi in frame_ticks]
    for (name, ys), colour in zip(series.items(), PALETTE):
        runs: list[list[tuple[float, float]]] = [[]]
        for xi, yi in zip(x, ys):
            if yi is None or not math.isfinite(yi):
                runs.append([])
            else:
                runs[-1].append((xi, yi))
        for run in filter(None, runs):
            if len(run) > 1:
                points = " ".join(f"{sx(a):.1f},{sy(b):.1f}" for a, b in run)
                parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" '
                             f'stroke-width="1.8"/>')
            if len(x) <= DOTS or len(run) == 1:
                parts += [f'<circle cx="{sx(a):.1f}" cy="{sy(b):.1f}" r="2.8" '
                          f'fill="{colour}"/>' for a, b in run]
            if len(x) <= LABELS:
                parts += [f'<text x="{sx(a):.1f}" y="{sy(b) - 6:.1f}" class="tick" '
                          f'text-anchor="{"end" if sx(a) > width / 2 else "start"}">'
                          f'{b:.3g}{escape(unit)}</text>' for a, b in run]
    if len(series) > 1:
        for i, (name, colour) in enumerate(zip(series, PALETTE)):
            x_legend = width - right - 110 * (len(series) - i)
            parts.append(f'<rect x="{x_legend}" y="6" width="9" height="9" fill="{colour}"/>'
                         f'<text x="{x_legend + 13}" y="14" class="tick">{escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)
