"""A field report as one self-contained HTML file: statistics, a slip map and charts drawn as
inline SVG, an inline style sheet, no script and nothing fetched (it opens offline, mails as
one file, prints).

The map draws the slip map's cells (:class:`~server.analytics.slipmap.SlipMap`) coloured by
mean ``|slip|`` (green 0 %, yellow at the first band edge, red from the last) under the track,
east right and north up at one scale; each chart draws its series (one polyline each) over
time, with its range and unit written on it. Times are UTC.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from server.analytics.slipmap import SlipMap
from server.timeparse import format_ns

__all__ = ["Chart", "Track", "field_report_html", "slip_colour"]

_W, _H, _PAD = 720.0, 220.0, 36.0
_MAP = 520.0
_LINE_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


@dataclass(frozen=True)
class Chart:
    """One chart: a title, a unit, and named series over ``stamp_ns`` (int64, shape (n,))."""

    title: str
    unit: str
    stamp_ns: np.ndarray
    series: dict[str, np.ndarray]


@dataclass(frozen=True)
class Track:
    """Positions of the drive in the map's frame: ``east_m``, ``north_m``, shape (n,)."""

    east_m: np.ndarray
    north_m: np.ndarray


def slip_colour(abs_slip_pct: float, band_edges_pct: Sequence[float]) -> str:
    """``#rrggbb`` of a cell: green at 0, yellow at the first edge, red from the last."""
    if not math.isfinite(abs_slip_pct):
        return "#cccccc"
    first, last = band_edges_pct[0], band_edges_pct[-1]
    if abs_slip_pct <= first:
        t = abs_slip_pct / first if first > 0 else 1.0
        r, g = 255 * t, 200.0
    else:
        t = min(1.0, (abs_slip_pct - first) / max(last - first, 1e-9))
        r, g = 255.0, 200 * (1 - t)
    return f"#{round(r):02x}{round(g):02x}30"


def _points(xs: np.ndarray, ys: np.ndarray) -> str:
    ok = np.isfinite(xs) & np.isfinite(ys)
    return " ".join(f"{x:.1f},{y:.1f}" for x, y in zip(xs[ok], ys[ok], strict=True))


def _chart_svg(chart: Chart) -> str:
    t = chart.stamp_ns.astype(np.float64)
    values = [v for v in chart.series.values() if np.isfinite(v).any()]
    if t.size < 2 or not values:
        return f"<p>{html.escape(chart.title)}: no data in the range.</p>"
    lo = float(min(np.nanmin(v) for v in values))
    hi = float(max(np.nanmax(v) for v in values))
    hi = hi if hi > lo else lo + 1.0
    x = _PAD + (t - t[0]) / max(t[-1] - t[0], 1.0) * (_W - 2 * _PAD)
    parts = [
        f'<svg viewBox="0 0 {_W:.0f} {_H:.0f}" role="img" class="chart">',
        f"<title>{html.escape(chart.title)}</title>",
        f'<rect x="{_PAD}" y="{_PAD / 2}" width="{_W - 2 * _PAD}" height="{_H - 1.5 * _PAD}" '
        'class="frame"/>',
        f'<text x="{_PAD}" y="{_PAD / 2 - 4}">{html.escape(chart.title)} '
        f"[{html.escape(chart.unit)}] {lo:.3g} to {hi:.3g}</text>",
        f'<text x="{_PAD}" y="{_H - 4}">{format_ns(int(chart.stamp_ns[0]))[:19]}Z</text>',
        f'<text x="{_W - _PAD}" y="{_H - 4}" text-anchor="end">'
        f"{format_ns(int(chart.stamp_ns[-1]))[:19]}Z</text>",
    ]
    for k, (name, v) in enumerate(chart.series.items()):
        y = _H - _PAD - (v - lo) / (hi - lo) * (_H - 1.5 * _PAD)
        colour = _LINE_COLOURS[k % len(_LINE_COLOURS)]
        parts.append(
            f'<polyline fill="none" stroke="{colour}" stroke-width="1.2" '
            f'points="{_points(x, y)}"><title>{html.escape(name)}</title></polyline>'
        )
        parts.append(
            f'<text x="{_W - _PAD - 4}" y="{_PAD / 2 + 14 * (k + 1)}" text-anchor="end" '
            f'fill="{colour}">{html.escape(name)}</text>'
        )
    return "\n".join([*parts, "</svg>"])


def _map_svg(smap: SlipMap | None, track: Track | None) -> str:
    """Cells and track at one scale, north up; nothing when there is neither."""
    es = [smap.east_m, smap.east_m + smap.cell_m] if smap is not None and smap.cells else []
    ns = [smap.north_m, smap.north_m + smap.cell_m] if smap is not None and smap.cells else []
    if track is not None:
        es.append(track.east_m)
        ns.append(track.north_m)
    east = np.concatenate(es) if es else np.zeros(0)
    north = np.concatenate(ns) if ns else np.zeros(0)
    ok = np.isfinite(east) & np.isfinite(north)
    if not ok.any():
        return "<p>No position in the range: no map.</p>"
    e0, e1, n0, n1 = east[ok].min(), east[ok].max(), north[ok].min(), north[ok].max()
    scale = (_MAP - 2 * _PAD) / max(e1 - e0, n1 - n0, 1.0)
    height = 2 * _PAD + (n1 - n0) * scale  # as tall as the drive, at the one scale

    def px(e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _PAD + (e - e0) * scale, height - _PAD - (n - n0) * scale

    parts = [f'<svg viewBox="0 0 {_MAP:.0f} {height:.0f}" role="img" class="map">']
    parts.append("<title>Slip map: mean |slip| per cell, and the track</title>")
    if smap is not None:
        x, y = px(smap.east_m, smap.north_m + smap.cell_m)
        side = smap.cell_m * scale
        for k in range(smap.cells):
            slip = float(smap.mean_abs_slip_pct[k])
            label = "no valid slip" if math.isnan(slip) else f"{slip:.1f} %"
            parts.append(
                f'<rect x="{x[k]:.1f}" y="{y[k]:.1f}" width="{side:.1f}" height="{side:.1f}" '
                f'fill="{slip_colour(slip, smap.band_edges_pct)}"><title>{label}</title></rect>'
            )
    if track is not None:
        tx, ty = px(track.east_m, track.north_m)
        parts.append(f'<polyline class="track" fill="none" points="{_points(tx, ty)}"/>')
    metres = 10 ** math.floor(math.log10(max((e1 - e0) / 4, 1.0)))
    parts.append(
        f'<line x1="{_PAD}" y1="{height - 12:.1f}" x2="{_PAD + metres * scale:.1f}" '
        f'y2="{height - 12:.1f}" class="scale"/>'
        f'<text x="{_PAD}" y="{height - 16:.1f}">{metres:g} m</text>'
    )
    parts.append(f'<text x="{_MAP - _PAD}" y="{_PAD - 8}" text-anchor="end">N ↑</text>')
    return "\n".join([*parts, "</svg>"])


_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222;max-width:60em}
table{border-collapse:collapse}td,th{padding:.2em .8em;border-bottom:1px solid #ddd;text-align:left}
svg{display:block;margin:1em 0;max-width:100%;font-size:11px}
.frame{fill:none;stroke:#999}.track{stroke:#222;stroke-width:1}.scale{stroke:#222;stroke-width:2}
"""


def field_report_html(
    title: str,
    facts: Sequence[tuple[str, str]],
    smap: SlipMap | None,
    track: Track | None,
    charts: Sequence[Chart],
) -> str:
    """The page: ``title``, a table of ``facts`` (label, value), the map, the charts."""
    rows = "\n".join(
        f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in facts
    )
    return "\n".join(
        [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
            f"<h1>{html.escape(title)}</h1>",
            f"<table>{rows}</table>",
            "<h2>Where the wheels slipped</h2>",
            _map_svg(smap, track),
            "<h2>Over time</h2>",
            *(_chart_svg(c) for c in charts),
            "</body></html>",
        ]
    )
