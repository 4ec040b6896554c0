"""Field reports: ``/vehicles/{id}/report`` and ``/fleet/report`` (JSON or CSV table)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response

from estimator.types import empty_estimates
from server.analytics.reports import REPORT_FIELDS, flatten_report, ingest_counts, vehicle_report
from server.api.deps import (
    LimitsDep,
    StoreDep,
    TimeRange,
    TimeRangeDep,
    VehicleDep,
    slip_config,
)
from server.api.errors import error_responses
from server.api.models import FleetReportPublic, VehicleReportPublic
from server.api.routes.series import export_filename
from server.api.tables import csv_table
from server.storage.base import Store, VehicleRecord

__all__ = ["REPORT_DESCRIPTION", "router"]

router = APIRouter(tags=["reports"])

REPORT_DESCRIPTION = """\
Over `start <= stamp < end` (at most 24 h by default; 400 `range_too_large` beyond):

* **time weight** of an estimate: the time to the next one; a step over 1 s is a gap (the estimate
  before it counts one median step); the last counts one median step. `covered_s` sums them.
* **moving**: `|vg_mps| >= slip.min_ground_speed_mps` of the vehicle's config; `moving_s`.
* **distance_m**: sum of `|vg_mps| · weight` over moving estimates.
* **speed**: time-weighted mean and median/p95 of `|vg_mps|` while moving; max over all.
* **slip per wheel**: estimates with the wheel's `SLIP_*_VALID` flag and a finite value; mean,
  median, p95 (linear interpolation), min, max of the **signed** slip in percent.
* **bands**: time share of **absolute** slip in `[0, e0)`, `[e0, e1)`, …, `[e_last, ∞)` with the
  edges `slip.band_edges_pct` of the vehicle's config (default 5 and 15 %); share of the wheel's
  valid-slip time.
* **degraded_s**: time flagged `DEGRADED` (GNSS lost).
* **ingest**: packet counter totals since registration (received, accepted, rejected by reason,
  late, duplicate, lost).
"""


def _report(
    store: Store, record: VehicleRecord, tr: TimeRange, max_gap_s: float
) -> VehicleReportPublic:
    slip = slip_config(record)
    rows = store.query_series(record.vehicle_id, tr.start_ns, tr.end_ns, REPORT_FIELDS)
    report = vehicle_report(
        rows,
        start_ns=tr.start_ns,
        end_ns=tr.end_ns,
        band_edges_pct=slip.band_edges_pct,
        min_ground_speed_mps=slip.min_ground_speed_mps,
        max_gap_s=max_gap_s,
    )
    return VehicleReportPublic(
        vehicle_id=record.vehicle_id,
        band_edges_pct=list(slip.band_edges_pct),
        report=report,
        ingest=ingest_counts(store.get_counters(record.vehicle_id)),
    )


ReportFormat = Annotated[Literal["json", "csv"], Query(description="Answer format")]


@router.get(
    "/vehicles/{vehicle_id}/report",
    response_model=VehicleReportPublic,
    responses={
        200: {
            "description": "The vehicle's report; CSV: one row, the columns of the fleet "
            "report's CSV.",
            "content": {"text/csv": {"schema": {"type": "string"}}},
        },
        **error_responses(400, 404, 422),
    },
    summary="Field report of one vehicle",
    description=REPORT_DESCRIPTION,
)
def get_vehicle_report(
    vehicle: VehicleDep,
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    format: ReportFormat = "json",
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    report = _report(store, vehicle, tr, limits.report_max_gap_s)
    if format == "csv":
        name = export_filename(f"{vehicle.vehicle_id}_report", tr, "csv")
        return _csv_response([report], name)
    return Response(report.model_dump_json(), media_type="application/json")


def _csv_response(reports: list[VehicleReportPublic], filename: str) -> Response:
    """One CSV row per report (:func:`server.analytics.reports.flatten_report`), as a download."""
    rows = [flatten_report(r.vehicle_id, r.report, r.ingest) for r in reports]
    if rows:
        columns: dict[str, None] = {}
        for row in rows:  # band columns: the union over the reports, empty where not used
            columns.update(dict.fromkeys(row))
        table = csv_table(list(columns), rows)
    else:  # an empty fleet still gets the header of the default-config columns
        empty = vehicle_report(empty_estimates(0)[list(REPORT_FIELDS)], start_ns=0, end_ns=1)
        table = csv_table(list(flatten_report("", empty, ingest_counts({}))), [])
    return Response(
        table,
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


@router.get(
    "/fleet/report",
    response_model=FleetReportPublic,
    responses={
        200: {
            "description": "One report per registered vehicle; CSV: one row per vehicle, band "
            "columns named by their edges (the union over the fleet, empty where not used).",
            "content": {"text/csv": {"schema": {"type": "string"}}},
        },
        **error_responses(400, 422),
    },
    summary="Field report of every vehicle",
    description=REPORT_DESCRIPTION,
)
def get_fleet_report(
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    format: ReportFormat = "json",
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    reports = [
        _report(store, record, tr, limits.report_max_gap_s) for record in store.list_vehicles()
    ]
    if format == "csv":
        return _csv_response(reports, "fleet_report.csv")
    body = FleetReportPublic(start_ns=tr.start_ns, end_ns=tr.end_ns, vehicles=reports)
    return Response(body.model_dump_json(), media_type="application/json")
