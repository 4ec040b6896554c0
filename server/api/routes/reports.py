"""Field reports: ``/vehicles/{id}/report`` and ``/fleet/report`` (JSON or CSV table), of one
estimator's rows read through its spec (``?estimator=``, default each vehicle's primary)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response

from estimator.catalog import SPECS
from estimator.spec import EstimatorSpec
from server.analytics.reports import flatten_report, ingest_counts, report_fields, vehicle_report
from server.api.deps import (
    EstimatorDep,
    EstimatorQuery,
    LimitsDep,
    SettingsDep,
    StoreDep,
    TimeRange,
    TimeRangeDep,
    VehicleDep,
    estimator_spec,
    slip_config,
    vehicle_estimators,
)
from server.api.errors import error_responses
from server.api.field_report import html_report, html_response
from server.api.limits import WorkBudget
from server.api.models import FleetReportPublic, VehicleReportPublic
from server.api.routes.series import export_filename
from server.api.tables import csv_table
from server.storage.base import Store, VehicleRecord

__all__ = ["REPORT_DESCRIPTION", "router"]

router = APIRouter(tags=["reports"])

REPORT_DESCRIPTION = """\
Over `start <= stamp < end` (at most 24 h by default; 400 `range_too_large` beyond), of one
estimator's rows (`estimator`, default the vehicle's primary), read through its spec
(`GET /api/v1/estimators`):

* **time weight** of an estimate: the time to the next one; a step over 1 s is a gap (the estimate
  before it counts one median step); the last counts one median step. `covered_s` sums them.
* **moving**: `|v| >= slip.min_ground_speed_mps` of the vehicle's config, `v` the field of the
  spec's `motion` speed channel (`report.motion`, `report.motion_field`); `moving_s`. An
  estimator without one has no moving time, distance or speeds (null).
* **distance_m**: sum of `|v| · weight` over moving estimates.
* **speed**: time-weighted mean and median/p95 of `|v|` while moving; max over all.
* **slips**, per slip channel of the spec (by its key, e.g. `left`): estimates with the channel's
  `valid_flag` set (none: every estimate) and a finite value; mean, median, p95 (linear
  interpolation), min, max of the **signed** slip in percent. An estimator without slip channels
  gives `{}`.
* **bands**: time share of **absolute** slip in `[0, e0)`, `[e0, e1)`, …, `[e_last, ∞)` with the
  edges `slip.band_edges_pct` of the vehicle's config (default 5 and 15 %); share of the
  channel's valid-slip time.
* **degraded_s**: time with any of the spec's `degraded_flags` set (its main reference lost).
* **ingest**: packet counter totals since registration (received, accepted, rejected by reason,
  late, duplicate, lost).
"""


def _report(
    store: Store, record: VehicleRecord, spec: EstimatorSpec, tr: TimeRange, max_gap_s: float
) -> VehicleReportPublic:
    slip = slip_config(record)
    rows = store.query_series(
        record.vehicle_id, tr.start_ns, tr.end_ns, report_fields(spec), estimator=spec.name
    )
    report = vehicle_report(
        rows,
        spec,
        start_ns=tr.start_ns,
        end_ns=tr.end_ns,
        band_edges_pct=slip.band_edges_pct,
        min_ground_speed_mps=slip.min_ground_speed_mps,
        max_gap_s=max_gap_s,
    )
    return VehicleReportPublic(
        vehicle_id=record.vehicle_id,
        estimator=spec.name,
        band_edges_pct=list(slip.band_edges_pct),
        report=report,
        ingest=ingest_counts(store.get_counters(record.vehicle_id)),
    )


def _primary(record: VehicleRecord) -> EstimatorSpec | None:
    """The vehicle's primary estimator's spec; None when it runs none."""
    names = vehicle_estimators(record)
    return SPECS.get(names[0]) if names else None


_FLEET_BUDGETS = """
**Budgets** (413 with one line naming the setting): a fleet of more than
`api.report_max_vehicles` vehicles is refused before anything is read; a report still working
after `api.report_time_budget_s` stops between two vehicles (narrow `start..end`).
"""

#: The spec with the fewest columns (no slip channel): the header of an empty fleet's table.
_NO_SLIP = min(SPECS.values(), key=lambda spec: len(spec.slips))

ReportFormat = Annotated[Literal["json", "csv"], Query(description="Answer format")]
VehicleReportFormat = Annotated[
    Literal["json", "csv", "html"],
    Query(description="Answer format; html: one self-contained page with the map and charts"),
]


@router.get(
    "/vehicles/{vehicle_id}/report",
    response_model=VehicleReportPublic,
    responses={
        200: {
            "description": "The vehicle's report; CSV: one row, the columns of the fleet "
            "report's CSV.",
            "content": {
                "text/csv": {"schema": {"type": "string"}},
                "text/html": {"schema": {"type": "string"}},
            },
        },
        **error_responses(400, 404, 422),
    },
    summary="Field report of one vehicle",
    description=REPORT_DESCRIPTION,
)
def get_vehicle_report(
    vehicle: VehicleDep,
    spec: EstimatorDep,
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    format: VehicleReportFormat = "json",
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    report = _report(store, vehicle, spec, tr, limits.report_max_gap_s)
    if format == "html":
        page = html_report(store, vehicle, spec, tr, limits, report.report)
        return html_response(page, export_filename(f"{vehicle.vehicle_id}_report", tr, "html"))
    if format == "csv":
        name = export_filename(f"{vehicle.vehicle_id}_report", tr, "csv")
        return _csv_response([report], name)
    return Response(report.model_dump_json(), media_type="application/json")


def _csv_response(reports: list[VehicleReportPublic], filename: str) -> Response:
    """One CSV row per report (:func:`server.analytics.reports.flatten_report`), as a download."""
    rows = [flatten_report(r.vehicle_id, r.estimator, r.report, r.ingest) for r in reports]
    columns: dict[str, None] = {}
    for row in rows:  # channel and band columns: the union over the reports, empty where unused
        columns.update(dict.fromkeys(row))
    if not rows:  # an empty fleet still gets the columns every report has
        empty = vehicle_report(_NO_SLIP.empty_rows(0), _NO_SLIP, start_ns=0, end_ns=1)
        columns.update(dict.fromkeys(flatten_report("", "", empty, ingest_counts({}))))
    table = csv_table(list(columns), rows)
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
            "description": "One report per registered vehicle, of `estimator` or else of each "
            "vehicle's primary (a vehicle that runs no estimator is left out); CSV: one row per "
            "vehicle, slip columns named by channel key and band edges (the union over the "
            "fleet, empty where not used).",
            "content": {"text/csv": {"schema": {"type": "string"}}},
        },
        **error_responses(400, 413, 422),
    },
    summary="Field report of every vehicle",
    description=REPORT_DESCRIPTION + _FLEET_BUDGETS,
)
def get_fleet_report(
    tr: TimeRangeDep,
    store: StoreDep,
    limits: LimitsDep,
    settings: SettingsDep,
    format: ReportFormat = "json",
    estimator: EstimatorQuery = None,
) -> Response:
    tr.check_span(limits.report_max_range_ns)
    asked = None if estimator is None else estimator_spec(estimator)
    records = store.list_vehicles()
    budget = WorkBudget(
        "the fleet report",
        len(records),
        "vehicles",
        max_items=(settings.api.report_max_vehicles, "api.report_max_vehicles"),
        time_budget_s=(settings.api.report_time_budget_s, "api.report_time_budget_s"),
    )
    reports = []
    for done, record in enumerate(records):
        budget.check(done)
        spec = asked or _primary(record)
        if spec is not None:
            reports.append(_report(store, record, spec, tr, limits.report_max_gap_s))
    if format == "csv":
        return _csv_response(reports, "fleet_report.csv")
    body = FleetReportPublic(start_ns=tr.start_ns, end_ns=tr.end_ns, vehicles=reports)
    return Response(body.model_dump_json(), media_type="application/json")
