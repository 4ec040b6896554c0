"""``/vehicles/{id}/report?format=html``: the field report as one self-contained HTML file.

Reads what the page shows, within the report's range: the report itself, the slip map (cells
of :data:`CELL_M`, coarser when a field would need more than the server's cell limit), and the
spec's charts and track thinned to at most :data:`MAX_POINTS` rows; the page is drawn by
:mod:`server.analytics.field_report_html`.
"""

from __future__ import annotations

import numpy as np
from fastapi import Response

from estimator.spec import EstimatorSpec
from server.analytics.field_report_html import Chart, Track, field_report_html
from server.analytics.reports import VehicleReport
from server.analytics.slipmap import NotMappable, SlipMap, TooManyCells, slipmap_fields
from server.api.deps import ApiLimits, TimeRange, slip_config, vehicle_slip_map
from server.storage.base import Store, VehicleRecord
from server.timeparse import format_ns

__all__ = ["CELL_M", "MAX_POINTS", "html_report", "html_response"]

#: Cell sides tried for the report's map, finest first.
CELL_M = (10.0, 50.0, 250.0)
#: Rows drawn per chart and in the track, at most.
MAX_POINTS = 1500


def _band(lower_pct: float, upper_pct: float | None) -> str:
    return f"≥ {lower_pct:g} %" if upper_pct is None else f"{lower_pct:g}–{upper_pct:g} %"


def _facts(vehicle_id: str, spec: EstimatorSpec, r: VehicleReport) -> list[tuple[str, str]]:
    def num(value: float | None, unit: str, digits: int = 1) -> str:
        return "–" if value is None else f"{value:.{digits}f} {unit}"

    facts = [
        ("Vehicle", vehicle_id),
        ("Estimator", f"{spec.title} ({spec.name})"),
        ("Range (UTC)", f"{format_ns(r.start_ns)[:19]}Z to {format_ns(r.end_ns)[:19]}Z"),
        ("Estimates", f"{r.rows} covering {r.covered_s:.0f} s"),
        ("Moving", num(r.moving_s, "s", 0)),
        ("Distance", num(r.distance_m, "m", 0)),
        ("Mean speed moving", num(r.speed.mean_mps, "m/s", 2)),
        ("Degraded", f"{r.degraded_s:.0f} s"),
    ]
    for s in r.slips.values():
        bands = ", ".join(
            f"{_band(b.lower_pct, b.upper_pct)}: "
            f"{'–' if b.share is None else f'{100 * b.share:.0f} %'}"
            for b in s.bands
        )
        stats = f"mean {num(s.mean_pct, '%')}, p95 {num(s.p95_pct, '%')}; {bands}"
        facts.append((f"Slip {s.label}", stats))
    return facts


def _map(
    rows: np.ndarray, record: VehicleRecord, spec: EstimatorSpec, tr: TimeRange, limits: ApiLimits
) -> SlipMap | None:
    slip = slip_config(record)
    for cell_m in CELL_M:
        try:
            return vehicle_slip_map(rows, spec, slip, tr, limits, cell_m)
        except TooManyCells:
            continue
    return None


def html_report(
    store: Store,
    record: VehicleRecord,
    spec: EstimatorSpec,
    tr: TimeRange,
    limits: ApiLimits,
    report: VehicleReport,
) -> str:
    """The page of ``report`` with its map and charts."""
    chart_fields = {f for c in spec.charts for f in c.fields}
    try:
        map_fields = set(slipmap_fields(spec))
    except NotMappable:
        map_fields = set()
    fields = sorted(chart_fields | map_fields | {"stamp_ns"})
    rows = store.query_series(record.vehicle_id, tr.start_ns, tr.end_ns, fields, spec.name)
    smap = _map(rows, record, spec, tr, limits) if map_fields else None
    thin = rows[:: max(1, -(-len(rows) // MAX_POINTS))]
    track = None
    if spec.position is not None:
        track = Track(thin[spec.position.east_field], thin[spec.position.north_field])
    label = {f.name: f.label or f.name for f in spec.fields}
    charts = [
        Chart(
            c.title,
            c.unit,
            thin["stamp_ns"],
            {label.get(f, f): thin[f].astype(np.float64) for f in c.fields},
        )
        for c in spec.charts
    ]
    title = f"Field report: {record.vehicle_id}"
    return field_report_html(title, _facts(record.vehicle_id, spec, report), smap, track, charts)


def html_response(page: str, filename: str) -> Response:
    """The page as a download named ``filename``."""
    return Response(
        page,
        media_type="text/html; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )
