"""Request and response models of the REST API (inputs and outputs kept apart).

Vehicle configs travel as plain JSON objects validated by
:func:`estimator.config.vehicle_config_from_dict` (so a client gets that function's reasons); their
OpenAPI schema is a union on ``kind`` built from the config dataclasses of
:mod:`estimator.config` and their ranges (:func:`estimator.config.bound_of`), so the two cannot
drift. Report bodies reuse the frozen dataclasses of :mod:`server.analytics.reports`.

Estimates are described per estimator from the catalog of specs (:data:`estimator.catalog.SPECS`):
one model per spec, told apart by ``estimator``, each field with its label, unit and description.
"""

from __future__ import annotations

import copy
import dataclasses
import typing
from typing import Annotated, Any, Literal, Union, cast

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StringConstraints,
    TypeAdapter,
    WithJsonSchema,
    create_model,
)

from estimator.catalog import SPECS
from estimator.config import (
    Bound,
    TrackedConfig,
    VehicleKind,
    Wheeled4wdSteeredConfig,
    WheeledRearDriveConfig,
    bound_of,
)
from estimator.spec import EstimatorSpec
from server.analytics.reports import IngestCounts, VehicleReport
from server.storage.base import Anchor

__all__ = [
    "ESTIMATE_MODELS",
    "CommandIn",
    "CommandPublic",
    "EstimatePublic",
    "EstimatorSpecPublic",
    "EstimatorsPublic",
    "FleetReportPublic",
    "FleetSlipMapCellPublic",
    "FleetSlipMapPublic",
    "FleetSlipMapVehiclePublic",
    "HealthPublic",
    "HealthUnavailable",
    "SeriesFormat",
    "SeriesPublic",
    "SlipChannelCellPublic",
    "SlipChannelRefPublic",
    "SlipMapCellPublic",
    "SlipMapFormat",
    "SlipMapPublic",
    "SlipMapSkippedPublic",
    "VehicleConfigAdapter",
    "VehicleConfigIn",
    "VehicleConfigOut",
    "VehiclePublic",
    "VehicleReportPublic",
    "VehiclesPublic",
    "fields_doc",
]

SeriesFormat = Literal["json", "csv", "parquet", "geojson"]
SlipMapFormat = Literal["json", "geojson", "csv", "isoxml"]


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


def _bounded_field(bound: Bound, default: Any) -> tuple[Any, Any]:
    """A pydantic field of a config number (or list of numbers) with its range and unit."""
    number: type = int if bound.integer else float
    text = f"{bound.doc}; {bound.describe()}"
    if bound.items is None and default is None:  # optional: null takes another source's
        return number | None, Field(None, ge=bound.low, le=bound.high, description=text)
    if bound.items is None:
        return number, Field(default, ge=bound.low, le=bound.high, description=text)
    item = Annotated[number, Field(ge=bound.low, le=bound.high)]  # type: ignore[valid-type]
    lo, hi = bound.items
    field = Field(list(default), min_length=lo, max_length=hi, description=text)
    return list[item], field


_EstimatorName = Annotated[str, StringConstraints(min_length=1, max_length=64)]


def _config_model(cls: type, models: dict[type, type[BaseModel]]) -> type[BaseModel]:
    """The pydantic model of config dataclass ``cls`` (sections built once, in ``models``)."""
    if cls in models:
        return models[cls]
    hints = typing.get_type_hints(cls)
    fields: dict[str, Any] = {}
    kind = getattr(cls, "kind", None)
    if kind is not None:  # optional for the default kind (an empty body registers one)
        default = kind.value if kind is VehicleKind.WHEELED_REAR_DRIVE else ...
        fields["kind"] = (Literal[kind.value], Field(default, description="the vehicle kind"))
    for f in dataclasses.fields(cls):
        bound = bound_of(f)
        if bound is not None:
            fields[f.name] = _bounded_field(bound, f.default)
        elif isinstance(f.default_factory, type):
            section = _config_model(f.default_factory, models)
            fields[f.name] = (section, Field(default_factory=section))
        elif f.name == "estimators":
            fields[f.name] = (
                list[_EstimatorName],
                Field(default_factory=list, max_length=8, description="empty: the kind's"),
            )
        else:  # a flag or a choice
            fields[f.name] = (hints[f.name], f.default)
    doc = (cls.__doc__ or "").strip().split("\n\n")[0]
    model = create_model(cls.__name__, __config__=ConfigDict(extra="forbid"), __doc__=doc, **fields)
    models[cls] = model
    return model


def _config_models() -> tuple[type[BaseModel], ...]:
    models: dict[type, type[BaseModel]] = {}
    kinds = (WheeledRearDriveConfig, TrackedConfig, Wheeled4wdSteeredConfig)
    return tuple(_config_model(cls, models) for cls in kinds)


VehicleConfigAdapter: TypeAdapter[Any] = TypeAdapter(
    # built at run time from the kinds' models, so typed as Any
    cast(Any, Annotated[Union[_config_models()], Field(discriminator="kind")])  # noqa: UP007
)
"""Checks the JSON types and ranges of a config of any kind (``kind`` present)."""


def _config_schema(*, request: bool) -> dict[str, Any]:
    """The union's JSON schema, inlined: one object per kind, told apart by ``kind``'s const.

    A request may omit ``kind`` (a rear-drive vehicle), so only answers, where every config
    names its kind, carry the OpenAPI discriminator (by property name: its mapping pointed into
    the ``$defs`` that inlining removes).
    """
    schema = _inline_refs(VehicleConfigAdapter.json_schema(), closed=request)
    schema.pop("discriminator", None)
    if not request:
        for member in schema["oneOf"]:
            member["required"] = sorted({"kind", *member.get("required", ())})
        schema["discriminator"] = {"propertyName": "kind"}
    return schema


VehicleConfigIn = Annotated[
    dict[str, Any],
    WithJsonSchema(
        {
            **_config_schema(request=True),
            "title": "VehicleConfigIn",
            "description": "Vehicle configuration of one kind (`wheeled_rear_drive` when "
            "`kind` is omitted); omitted parts take their defaults, unknown fields are "
            "refused, every number has its range and unit in its description.",
        }
    ),
]
"""Body of ``PUT /vehicles/{id}``: a vehicle config as JSON (validated by the handler)."""

VehicleConfigOut = Annotated[
    dict[str, Any],
    WithJsonSchema(
        {
            **_config_schema(request=False),
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


class CommandIn(BaseModel):
    """Turn an estimator's command on or off."""

    model_config = ConfigDict(extra="forbid")

    on: bool = Field(description="true: on; false: off")


class CommandPublic(BaseModel):
    """A command sent to the running estimator of one vehicle."""

    vehicle_id: str
    estimator: str
    command: str
    on: bool


class VehiclePublic(BaseModel):
    """A registered vehicle."""

    vehicle_id: str
    config: VehicleConfigOut
    created_ns: int = Field(description="registration time, ns since the epoch, UTC")
    updated_ns: int = Field(description="last config change, ns since the epoch, UTC")
    anchor: AnchorPublic | None = Field(
        default=None,
        description="origin of the local east/north/up frame of the estimates' positions (the "
        "vehicle's first GNSS fix with a position, kept for good); null until it is stored, "
        "a second or so after that fix",
    )
    estimators: list[str] = Field(
        default_factory=list,
        description="estimators the vehicle runs (`GET /api/v1/estimators`), its primary first: "
        "the default of every estimate route's `estimator`; empty when its config runs none",
    )


class VehiclesPublic(BaseModel):
    """Every registered vehicle."""

    data: list[VehiclePublic]
    count: int


def _field_doc(spec: EstimatorSpec, name: str) -> str:
    f = spec.field(name)
    unit = f" [{f.unit}]" if f.unit else ""
    return f"{f.label}{unit}: {f.description}" if f.description else f"{f.label}{unit}"


def fields_doc() -> str:
    """Every estimator's fields with their units, one line per estimator (for OpenAPI)."""
    return "\n".join(
        f"* `{spec.name}`: "
        + ", ".join(f"`{f.name}`" + (f" ({f.unit})" if f.unit else "") for f in spec.fields)
        for _, spec in sorted(SPECS.items())
    )


def _estimate_model(spec: EstimatorSpec) -> type[BaseModel]:
    """One row of ``spec`` as JSON: every field (floats null when not available) plus who, when
    and the decoded flags."""
    fields: dict[str, Any] = {
        "vehicle_id": (str, ...),
        "estimator": (Literal[spec.name], Field(description="the estimator of this row")),
        "time": (str, Field(description="stamp_ns as ISO 8601 UTC with nanoseconds")),
        "flag_names": (list[str], Field(description="names of the flags set in `flags`")),
    }
    for f in spec.fields:
        doc = _field_doc(spec, f.name)
        if f.kind == "f8":
            fields[f.name] = (float | None, Field(description=doc + "; null when not available"))
        else:
            fields[f.name] = (int, Field(description=doc))
    title = "".join(part.title() for part in spec.name.split("_"))
    return create_model(
        f"Estimate{title}Public",
        __config__=ConfigDict(extra="forbid", title=f"Estimate{title}Public"),
        __doc__=f"One row of the estimator `{spec.name}` ({spec.title}).",
        **fields,
    )


#: One response model per estimator of the catalog, by name.
ESTIMATE_MODELS: dict[str, type[BaseModel]] = {
    name: _estimate_model(spec) for name, spec in sorted(SPECS.items())
}

EstimatePublic: Any = Annotated[
    Union[tuple(ESTIMATE_MODELS.values())],  # noqa: UP007  (a union built from the catalog)
    Field(discriminator="estimator"),
]
"""One estimate row of any estimator, told apart by ``estimator``."""


class FieldSpecPublic(BaseModel):
    """One field of an estimator's row."""

    name: str
    kind: Literal["f8", "i8", "i4"] = Field(description="numpy type: float64, int64, int32")
    unit: str
    label: str
    description: str


class FlagSpecPublic(BaseModel):
    """One bit of an estimator's `flags` field."""

    name: str
    bit: int
    description: str


class SlipChannelSpecPublic(BaseModel):
    """A slip-like value of one wheel or track, in percent."""

    key: str
    label: str
    field: str
    position: str = Field(description="rear_left, rear_right, front_left, …, track_left, …")
    valid_flag: str | None = Field(description="flag marking a valid value; null: finite")
    std_field: str | None
    band_edges_pct: list[float]


class SpeedChannelSpecPublic(BaseModel):
    """A speed, m/s, forward positive."""

    key: str
    label: str
    field: str
    std_field: str | None


class PositionChannelSpecPublic(BaseModel):
    """Fields of the position in the vehicle's ENU frame (metres from its anchor)."""

    east_field: str
    north_field: str
    up_field: str | None
    heading_field: str | None
    carried_flag: str | None = Field(description="flag of a dead-reckoned position")
    pitch_field: str | None = Field(description="body pitch, rad (nose up positive)")
    roll_field: str | None = Field(description="body roll, rad (right side down positive)")
    east_std_field: str | None = Field(default=None, description="1-sigma of east, m")
    north_std_field: str | None = Field(default=None, description="1-sigma of north, m")


class ChartSpecPublic(BaseModel):
    """Fields one chart draws together."""

    key: str
    title: str
    unit: str
    fields: list[str]


class StateValuePublic(BaseModel):
    """One value of an enumerated field."""

    value: int
    name: str
    label: str


class StateChannelSpecPublic(BaseModel):
    """An enumerated (i4) field whose values name states; drawn as a band of stretches."""

    key: str
    label: str
    field: str
    states: list[StateValuePublic]
    confidence_field: str | None = Field(description="0..1 confidence of the state")
    uncertain_flag: str | None = Field(description="flag of a row whose state is uncertain")


class ValueChannelSpecPublic(BaseModel):
    """A headline value that is neither slip nor speed (friction μ)."""

    key: str
    label: str
    field: str
    unit: str
    std_field: str | None
    valid_flag: str | None = Field(description="flag of the rows that inform it; others hold")
    mapped: bool = Field(description="a layer of the slip map (`layer=<key>`)")


class WheelValueChannelSpecPublic(BaseModel):
    """A per-wheel share in percent other than slip (grip used)."""

    key: str
    label: str
    field: str
    position: str


class AlertRuleSpecPublic(BaseModel):
    """An alert the estimator's rows raise (kind ``rule:<estimator>:<key>``), its defaults."""

    key: str
    label: str
    field: str | None
    above: float | None
    below: float | None
    hold_s: float = Field(description="held this long in sensor time before it opens")
    slip: str | None = Field(description="the slip channel it watches in place of the threshold")


class CommandSpecPublic(BaseModel):
    """A switch an operator sends the running estimator for one vehicle."""

    key: str
    label: str
    description: str


class CalibrationChannelSpecPublic(BaseModel):
    """A quantity the estimator calibrates online per vehicle (its rows carry it)."""

    key: str
    label: str
    field: str = Field(description="row field of the value")
    std_field: str = Field(description="row field of its 1-sigma")
    limit_config: str = Field(description="vehicle config number the std converges below")
    limit_scale: float = Field(description="turns that number into the std's unit")
    relative: bool = Field(description="the limit is relative to |value|")
    enabled_config: str | None = Field(description="vehicle config switch that turns it on")


class EstimatorSpecPublic(BaseModel):
    """What an estimator takes and gives (``estimator.spec.EstimatorSpec.to_dict()``)."""

    name: str
    title: str
    description: str
    kinds: list[str] = Field(description="vehicle kinds it runs on")
    inputs: list[str] = Field(description="wire streams it reads")
    fields: list[FieldSpecPublic]
    flags: list[FlagSpecPublic]
    slips: list[SlipChannelSpecPublic]
    speeds: list[SpeedChannelSpecPublic]
    motion: str | None = Field(description="key of the speed channel that decides moving")
    position: PositionChannelSpecPublic | None
    charts: list[ChartSpecPublic]
    ok_flag: str | None
    degraded_flags: list[str]
    states: list[StateChannelSpecPublic] = []
    values: list[ValueChannelSpecPublic] = []
    wheel_values: list[WheelValueChannelSpecPublic] = []
    alerts: list[AlertRuleSpecPublic] = []
    commands: list[CommandSpecPublic] = []
    calibrations: list[CalibrationChannelSpecPublic] = []
    uncalibrated_flag: str | None = None


class EstimatorsPublic(BaseModel):
    """Every estimator the server knows, by name."""

    data: list[EstimatorSpecPublic]
    count: int


class SeriesPublic(BaseModel):
    """A series as column arrays: ``columns[field][i]`` is row ``i``; NaN is null."""

    vehicle_id: str
    estimator: str = Field(description="the estimator whose fields `columns` holds")
    start_ns: int
    end_ns: int
    fields: list[str]
    units: dict[str, str] = Field(description="unit of each field (spec; '' for counts, bits)")
    flag_bits: dict[str, int] = Field(description="bit of each flag of `flags`, by name")
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
    """Field report of one vehicle's estimator (definitions in the API description of the route)."""

    vehicle_id: str
    estimator: str
    band_edges_pct: list[float] = Field(description="the vehicle's slip band edges")
    report: VehicleReport
    ingest: IngestCounts


class FleetReportPublic(BaseModel):
    """The report of every registered vehicle over one range."""

    start_ns: int
    end_ns: int
    vehicles: list[VehicleReportPublic]


class SlipChannelCellPublic(BaseModel):
    """One slip channel in one cell."""

    valid_s: float = Field(description="time with a valid slip of the channel")
    mean_pct: float | None = Field(description="time-weighted mean signed slip")


class SlipChannelRefPublic(BaseModel):
    """A slip channel of the map's estimator (`slips` keys of the cells)."""

    key: str
    label: str
    field: str


class LayerCellPublic(BaseModel):
    """A map layer (a value channel, e.g. friction μ) in one cell."""

    valid_s: float = Field(description="time of the samples that inform the layer")
    mean: float | None = Field(description="time-weighted mean over those samples")
    samples: int = Field(description="how many samples inform the layer")


class SlipMapCellPublic(BaseModel):
    """One cell of a slip map (definitions in the API description of the route)."""

    index_east: int = Field(description="i = floor(east / cell_m)")
    index_north: int = Field(description="j = floor(north / cell_m)")
    east_m: float = Field(description="east of the cell's south-west corner, i · cell_m")
    north_m: float = Field(description="north of the cell's south-west corner, j · cell_m")
    time_s: float = Field(description="moving time in the cell")
    distance_m: float
    rows: int = Field(description="moving estimates in the cell")
    slips: dict[str, SlipChannelCellPublic] = Field(
        description="per slip channel of the estimator, by key (`slip_channels`)"
    )
    mean_abs_slip_pct: float | None = Field(
        description="time-weighted mean |slip| over every slip channel's valid slips"
    )
    max_abs_slip_pct: float | None
    slip_band_shares: dict[str, float | None] = Field(
        description="time share of |slip| in each band, by band label (`0_5`, `5_15`, "
        "`15_up`); null without valid slip time"
    )
    layer: LayerCellPublic | None = Field(
        default=None, description="the map layer's statistics (null without `layer=`)"
    )


class SlipMapPublic(BaseModel):
    """A vehicle's slip map: the cells it drove through while moving, in its own ENU frame."""

    vehicle_id: str
    estimator: str
    slip_channels: list[SlipChannelRefPublic]
    layer: ValueChannelSpecPublic | None = Field(
        default=None, description="the map layer (a value channel of the estimator), if asked"
    )
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
    reason: Literal["no_anchor", "other_estimator"] = Field(
        description="`no_anchor`: no position stored yet, so its frame cannot be placed; "
        "`other_estimator`: its primary estimator is not the map's (no `estimator=` given)"
    )


class FleetSlipMapPublic(BaseModel):
    """The slip map of several vehicles in one shared ENU frame."""

    estimator: str | None = Field(
        description="the estimator mapped (null: none given and no vehicle placed)"
    )
    slip_channels: list[SlipChannelRefPublic]
    layer: ValueChannelSpecPublic | None = Field(
        default=None, description="the map layer (a value channel of the estimator), if asked"
    )
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
