"""Request and response models of the REST API (inputs and outputs kept apart).

Vehicle configs travel as plain JSON objects validated by
:func:`estimator.config.vehicle_config_from_dict` (so a client gets that function's reasons); their
OpenAPI schema is generated from :class:`estimator.config.VehicleConfig` itself, so the two cannot
drift. Report bodies reuse the frozen dataclasses of :mod:`server.analytics.reports`.
"""

from __future__ import annotations

import copy
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, WithJsonSchema, create_model

from estimator.config import VehicleConfig
from estimator.types import ESTIMATE_FIELDS
from server.analytics.reports import IngestCounts, VehicleReport
from server.storage.base import Anchor

__all__ = [
    "ESTIMATE_FIELD_NAMES",
    "EstimatePublic",
    "FleetReportPublic",
    "FleetSlipMapCellPublic",
    "FleetSlipMapPublic",
    "FleetSlipMapVehiclePublic",
    "HealthPublic",
    "HealthUnavailable",
    "SeriesFormat",
    "SeriesPublic",
    "SlipMapCellPublic",
    "SlipMapFormat",
    "SlipMapPublic",
    "SlipMapSkippedPublic",
    "VehicleConfigIn",
    "VehicleConfigOut",
    "VehiclePublic",
    "VehicleReportPublic",
    "VehiclesPublic",
]

ESTIMATE_FIELD_NAMES: tuple[str, ...] = tuple(name for name, _ in ESTIMATE_FIELDS)

SeriesFormat = Literal["json", "csv", "parquet", "geojson"]
SlipMapFormat = Literal["json", "geojson", "csv"]


def _inline_refs(schema: dict[str, Any], *, closed: bool) -> dict[str, Any]:
    """Replace local ``$ref``s by their ``$defs`` (an OpenAPI-safe, self-contained schema).

    ``closed`` adds ``additionalProperties: false`` to every object with properties.
    """
    defs = schema.get("$defs", {})

    def walk(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                return walk(copy.deepcopy(defs[ref.removeprefix("#/$defs/")]))
            out = {k: walk(v) for k, v in node.items() if k != "$defs"}
            prefix = out.get("prefixItems")
            if isinstance(prefix, list) and prefix and all(p == prefix[0] for p in prefix):
                # fixed-length tuple of one type: plain ``items`` (client generators know it)
                out["items"] = out.pop("prefixItems")[0]
            if closed and out.get("type") == "object" and "properties" in out:
                out["additionalProperties"] = False
            return out
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    result: dict[str, Any] = walk(schema)
    return result


_CONFIG_SCHEMA = TypeAdapter(VehicleConfig).json_schema()

VehicleConfigIn = Annotated[
    dict[str, Any],
    WithJsonSchema(
        {
            **_inline_refs(_CONFIG_SCHEMA, closed=True),
            "title": "VehicleConfigIn",
            "description": "Vehicle configuration; omitted parts take their defaults, unknown "
            "fields are refused.",
        }
    ),
]
"""Body of ``PUT /vehicles/{id}``: a VehicleConfig as JSON (validated by the handler)."""

VehicleConfigOut = Annotated[
    dict[str, Any],
    WithJsonSchema(
        {
            **_inline_refs(_CONFIG_SCHEMA, closed=False),
            "title": "VehicleConfigOut",
            "description": "Vehicle configuration as stored (every field present).",
        }
    ),
]


class AnchorPublic(BaseModel):
    """Origin of a vehicle's local ENU frame (WGS 84)."""

    lat_deg: float
    lon_deg: float
    height_m: float = Field(description="ellipsoidal height")

    @classmethod
    def of(cls, anchor: Anchor) -> AnchorPublic:
        """The stored ``(lat, lon, height)`` by name (one shape in every answer that has one)."""
        lat_deg, lon_deg, height_m = anchor
        return cls(lat_deg=lat_deg, lon_deg=lon_deg, height_m=height_m)

    @classmethod
    def as_json(cls, anchor: Anchor | None) -> dict[str, float] | None:
        """:meth:`of` as a plain object for a hand-built JSON body; None while there is none."""
        return None if anchor is None else cls.of(anchor).model_dump()


class VehiclePublic(BaseModel):
    """A registered vehicle."""

    vehicle_id: str
    config: VehicleConfigOut
    created_ns: int = Field(description="registration time, ns since the epoch, UTC")
    updated_ns: int = Field(description="last config change, ns since the epoch, UTC")
    anchor: AnchorPublic | None = Field(
        default=None,
        description="origin of the frame of the estimates' east_m, north_m and up_m (the "
        "vehicle's first GNSS fix with a position, kept for good); null until it is stored, "
        "a second or so after that fix",
    )


class VehiclesPublic(BaseModel):
    """Every registered vehicle."""

    data: list[VehiclePublic]
    count: int


def _estimate_fields() -> dict[str, Any]:
    fields: dict[str, Any] = {}
    for name, kind in ESTIMATE_FIELDS:
        if kind == "f8":
            fields[name] = (float | None, Field(description="null when not available"))
        else:
            fields[name] = (int, ...)
    return fields


_EstimateBase: type[BaseModel] = create_model(
    "EstimateFieldsPublic", __config__=ConfigDict(extra="forbid"), **_estimate_fields()
)


class EstimatePublic(_EstimateBase):
    """One estimate row: every field of ``ESTIMATE_DTYPE`` (units in the names, slip in %)."""

    vehicle_id: str
    time: str = Field(description="stamp_ns as ISO 8601 UTC with nanoseconds")
    flag_names: list[str] = Field(description="names of the EstimateFlag bits set in flags")


class SeriesPublic(BaseModel):
    """A series as column arrays: ``columns[field][i]`` is row ``i``; NaN is null."""

    vehicle_id: str
    start_ns: int
    end_ns: int
    fields: list[str]
    max_points: int = Field(description="0 means full rate")
    decimation: Literal["minmax", "first"] = Field(
        description="minmax: per bucket the min and max of each field (rows mix estimates); "
        "first: per bucket its first row, whole"
    )
    downsampled: bool = Field(description="true when rows were decimated (see decimation)")
    bucket_ns: int = Field(
        description="width of one time bucket, sized on the stored rows' span; 0 at full rate"
    )
    rows: int = Field(description="rows in this answer")
    stored_rows: int = Field(description="rows stored in the range")
    first_ns: int | None = Field(description="stamp of the first stored row in the range")
    last_ns: int | None = Field(description="stamp of the last stored row in the range")
    columns: dict[str, list[float | int | None]]


class VehicleReportPublic(BaseModel):
    """Field report of one vehicle (definitions in the API description of the route)."""

    vehicle_id: str
    band_edges_pct: list[float]
    report: VehicleReport
    ingest: IngestCounts


class FleetReportPublic(BaseModel):
    """The report of every registered vehicle over one range."""

    start_ns: int
    end_ns: int
    vehicles: list[VehicleReportPublic]


class SlipMapCellPublic(BaseModel):
    """One cell of a slip map (definitions in the API description of the route)."""

    index_east: int = Field(description="i = floor(east_m / cell_m)")
    index_north: int = Field(description="j = floor(north_m / cell_m)")
    east_m: float = Field(description="east of the cell's south-west corner, i · cell_m")
    north_m: float = Field(description="north of the cell's south-west corner, j · cell_m")
    time_s: float = Field(description="moving time in the cell")
    distance_m: float
    rows: int = Field(description="moving estimates in the cell")
    slip_left_valid_s: float = Field(description="time with a valid left-wheel slip")
    slip_right_valid_s: float = Field(description="time with a valid right-wheel slip")
    slip_left_mean_pct: float | None = Field(description="time-weighted mean signed slip")
    slip_right_mean_pct: float | None = Field(description="time-weighted mean signed slip")
    mean_abs_slip_pct: float | None = Field(description="time-weighted mean |slip|, both wheels")
    max_abs_slip_pct: float | None
    slip_band_shares: dict[str, float | None] = Field(
        description="time share of |slip| in each band, by band label (`0_5`, `5_15`, "
        "`15_up`); null without valid slip time"
    )


class SlipMapPublic(BaseModel):
    """A vehicle's slip map: the cells it drove through while moving, in its own ENU frame."""

    vehicle_id: str
    start_ns: int
    end_ns: int
    cell_m: float
    anchor: AnchorPublic | None = Field(
        description="origin of the frame the cells are cut in (null: no position known yet)"
    )
    band_edges_pct: list[float]
    band_labels: list[str]
    count: int = Field(description="number of cells")
    cells: list[SlipMapCellPublic]


class FleetSlipMapCellPublic(SlipMapCellPublic):
    """One cell of a fleet slip map: the sums over every vehicle's samples in it."""

    vehicles: int = Field(description="vehicles with samples in the cell")


class FleetSlipMapVehiclePublic(BaseModel):
    """A vehicle placed in a fleet slip map."""

    vehicle_id: str
    rows: int = Field(description="its samples in the map (moving estimates with a position)")
    cells: int = Field(description="cells it has samples in")


class SlipMapSkippedPublic(BaseModel):
    """A vehicle left out of a fleet slip map, and why."""

    vehicle_id: str
    reason: Literal["no_anchor"] = Field(
        description="`no_anchor`: no position stored yet, so its frame cannot be placed"
    )


class FleetSlipMapPublic(BaseModel):
    """The slip map of several vehicles in one shared ENU frame."""

    start_ns: int
    end_ns: int
    cell_m: float
    origin: AnchorPublic | None = Field(
        description="origin of the shared frame the cells are cut in (null: no origin given and "
        "no vehicle has a stored anchor; then there are no cells)"
    )
    origin_vehicle_id: str | None = Field(
        description="the vehicle whose anchor is the origin; null when the origin was given"
    )
    band_edges_pct: list[float]
    band_labels: list[str]
    band_edges_source: Literal["query", "vehicles", "default"] = Field(
        description="`query`: the band_edges_pct parameter; `vehicles`: the edges every placed "
        "vehicle's config has; `default`: 5 and 15 % (none given and the configs differ)"
    )
    vehicles: list[FleetSlipMapVehiclePublic] = Field(description="placed vehicles, by id")
    skipped: list[SlipMapSkippedPublic] = Field(description="vehicles left out, by id")
    count: int = Field(description="number of cells")
    cells: list[FleetSlipMapCellPublic]


class HealthPublic(BaseModel):
    """Every part is up."""

    status: Literal["ok"]
    checks: dict[str, bool]


class HealthUnavailable(BaseModel):
    """A part is down: ``checks`` says which."""

    error: str
    reason: str
    checks: dict[str, bool]
