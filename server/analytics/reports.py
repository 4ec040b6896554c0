"""Field reports over one estimator's series (pure numpy, no I/O), read through its spec.

Every number is defined from the estimator's :class:`estimator.spec.EstimatorSpec`, never from
one estimator's field names: "moving" from its ``motion`` speed channel, slip from its slip
channels, "degraded" from its ``degraded_flags``.

Definitions (what every number in a report means)
-------------------------------------------------
Time weight of a row
    Row ``i`` stands for the time until the next row, ``w_i = t[i+1] - t[i]``. A step longer than
    ``max_gap_s`` is a data gap: the row before it counts one nominal period ``T`` (the median
    step) instead, and the gap itself counts as no data. The last row counts ``T`` too, clipped to
    the end of the report range. ``covered_s = Σ w_i``.
Moving
    A row is moving when ``|v| >= min_ground_speed_mps`` (the vehicle's ``SlipConfig``), ``v``
    the spec's motion field (``spec.motion_field``). ``moving_s = Σ w_i`` over moving rows. A
    spec without a motion channel has no moving time, distance or speed (None).
Distance
    ``distance_m = Σ |v|_i · w_i`` over moving rows (sample-and-hold integration of the motion
    speed; reversing adds distance too). So ``distance_m / moving_s`` is the time-weighted mean
    moving speed.
Speed statistics
    ``mean_mps`` is that time-weighted mean; ``median_mps`` and ``p95_mps`` are over the moving
    rows' ``|v|`` samples; ``max_mps`` is the largest ``|v|`` of any row.
Slip statistics, per slip channel
    Over rows where the channel's ``valid_flag`` is set (a channel without one: every row) and
    whose slip is finite. ``mean_pct``, ``median_pct``, ``p95_pct``, ``min_pct``, ``max_pct`` are
    of the **signed** slip in percent (traction slip positive, skid negative), per sample.
    Percentiles interpolate linearly between samples.
Slip bands, per slip channel
    Time share of **absolute** slip ``|s|`` in the bands cut by the edges ``(e0, e1, …)`` (the
    vehicle's ``band_edges_pct``, else the channel's): ``[0, e0)``, ``[e0, e1)``, …,
    ``[e_last, ∞)`` — a value equal to an edge belongs to the upper band. Absolute, because a
    20 % skid wears and compacts like a 20 % spin. ``seconds = Σ w_i`` of valid rows in the
    band; ``share = seconds / Σ w_i`` of valid rows.
Degraded time
    ``degraded_s = Σ w_i`` over rows with any of the spec's ``degraded_flags`` set.
Per state (a spec with a ``state`` channel: a crawler's motion state)
    For each label of the channel, ``seconds = Σ w_i`` and ``distance_m = Σ |v|_i · w_i`` over
    the moving rows in that state, and per slip channel the signed ``mean_pct`` and ``p95_pct``
    of its valid samples in that state (None: none). States never seen are left out.
Ingest counters
    Totals since the vehicle was registered (the store keeps totals, not a history), split into
    the named counts and the ``rejected_<reason>`` counters; ``lost`` is the ingest's
    ``lost_by_seq_gap`` (sequence numbers that never arrived).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

import numpy as np

from estimator.spec import EstimatorSpec, SlipChannel, StateChannel

__all__ = [
    "ChannelSlipStats",
    "IngestCounts",
    "SlipBand",
    "SpeedStats",
    "StateStats",
    "VehicleReport",
    "band_bounds",
    "band_index",
    "band_label",
    "channel_edges",
    "channel_slips",
    "check_band_edges",
    "degraded_rows",
    "flatten_report",
    "ingest_counts",
    "motion_speed",
    "report_fields",
    "time_weights_ns",
    "vehicle_report",
]

_NS = 1_000_000_000


def report_fields(spec: EstimatorSpec) -> list[str]:
    """The fields of ``spec`` a report reads (ask the store for these only): ``stamp_ns``, the
    motion field, each slip channel's field and ``flags`` when the spec has one."""
    state = spec.states[0].field if spec.states else None
    wanted = ["stamp_ns", spec.motion_field, state, *(s.field for s in spec.slips)]
    if spec.has_field("flags"):
        wanted.append("flags")
    return list(dict.fromkeys(f for f in wanted if f is not None))


@dataclass(frozen=True, slots=True)
class SlipBand:
    """Time spent with ``lower_pct <= |slip| < upper_pct`` (``upper_pct`` None: no upper edge)."""

    lower_pct: float
    upper_pct: float | None
    seconds: float
    share: float | None  # of the channel's valid-slip time; None when there is none


@dataclass(frozen=True, slots=True)
class ChannelSlipStats:
    """Slip of one slip channel over the report range (signed percent; NaN-free samples only).

    ``label`` and ``field`` are the channel's (:class:`estimator.spec.SlipChannel`);
    ``band_edges_pct`` the edges its ``bands`` are cut by.
    """

    label: str
    field: str
    band_edges_pct: tuple[float, ...]
    samples: int
    valid_s: float
    mean_pct: float | None
    median_pct: float | None
    p95_pct: float | None
    min_pct: float | None
    max_pct: float | None
    bands: tuple[SlipBand, ...]


@dataclass(frozen=True, slots=True)
class SpeedStats:
    """Motion speed ``|v|``: mean/median/p95 while moving, max over all rows (None: none)."""

    mean_mps: float | None
    median_mps: float | None
    p95_mps: float | None
    max_mps: float | None


@dataclass(frozen=True, slots=True)
class StateStats:
    """Time, distance and slip in one state of the spec's state channel (module docstring):
    ``slip_mean_pct`` / ``slip_p95_pct`` per slip channel key (None: no valid sample)."""

    label: str
    seconds: float
    distance_m: float | None
    slip_mean_pct: dict[str, float | None]
    slip_p95_pct: dict[str, float | None]


@dataclass(frozen=True, slots=True)
class IngestCounts:
    """Packet counters of one vehicle (totals, see the module docstring)."""

    received: int = 0
    accepted: int = 0
    rejected: int = 0
    rejected_by_reason: dict[str, int] = field(default_factory=dict)
    late: int = 0
    duplicate: int = 0
    lost: int = 0
    other: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class VehicleReport:
    """Everything a field report says about one vehicle's estimator over ``[start_ns, end_ns)``.

    ``motion`` / ``motion_field``: the speed channel (key and field) that decides "moving", None
    when the spec has none (then ``moving_s``, ``distance_m`` and the speeds are None).
    ``slips``: per slip channel key, in the spec's order; ``states``: per state label of the
    spec's state channel, in its order (empty without one).
    """

    start_ns: int
    end_ns: int
    rows: int
    first_stamp_ns: int | None
    last_stamp_ns: int | None
    covered_s: float
    motion: str | None
    motion_field: str | None
    moving_s: float | None
    distance_m: float | None
    degraded_s: float
    speed: SpeedStats
    slips: dict[str, ChannelSlipStats]
    states: dict[str, StateStats] = field(default_factory=dict)


_NAMED_COUNTERS = ("received", "accepted", "late", "duplicate", "lost")
_REJECTED_PREFIXES = ("rejected_", "rejected.")


def ingest_counts(counters: Mapping[str, int]) -> IngestCounts:
    """Split a store's counter totals into named counts and rejection reasons.

    Names follow :mod:`server.ingest.counters`: ``received``, ``accepted``, ``late``,
    ``duplicate``, ``rejected_<reason>`` (or ``rejected.<reason>``) and ``lost_by_seq_gap``
    (reported as ``lost``; a plain ``lost`` wins). ``rejected`` is the sum of the reasons unless
    the store keeps a plain ``rejected`` total, which then wins. Anything else is ``other``.
    """
    named = {k: int(counters.get(k, 0)) for k in _NAMED_COUNTERS}
    if "lost" not in counters:
        named["lost"] = int(counters.get("lost_by_seq_gap", 0))
    by_reason: dict[str, int] = {}
    other: dict[str, int] = {}
    for key, value in counters.items():
        if key in _NAMED_COUNTERS or key in ("rejected", "lost_by_seq_gap"):
            continue
        prefix = next((p for p in _REJECTED_PREFIXES if key.startswith(p)), None)
        if prefix is not None:
            by_reason[key[len(prefix) :]] = int(value)
        else:
            other[key] = int(value)
    rejected = int(counters["rejected"]) if "rejected" in counters else sum(by_reason.values())
    return IngestCounts(
        rejected=rejected,
        rejected_by_reason=dict(sorted(by_reason.items())),
        other=dict(sorted(other.items())),
        **named,
    )


def time_weights_ns(stamps: np.ndarray, end_ns: int, max_gap_ns: int) -> np.ndarray:
    """``w_i`` of every row in ns (see the module docstring), int64, shape (n,).

    ``stamps`` : int64, shape (n,), sorted; ``end_ns`` clips the last row's weight.
    """
    n = stamps.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    steps = np.diff(stamps)
    good = steps[(steps > 0) & (steps <= max_gap_ns)]
    period = int(np.median(good)) if good.size else 0
    w = np.empty(n, dtype=np.int64)
    w[:-1] = np.where(steps <= max_gap_ns, steps, period)
    w[-1] = max(min(period, int(end_ns) - int(stamps[-1])), 0)
    return w


def motion_speed(
    rows: np.ndarray, spec: EstimatorSpec, min_ground_speed_mps: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(|v|, moving)`` of every row, float64 and bool, shape (n,) each; None when ``spec``
    has no motion channel.

    ``v`` is ``spec.motion_field``; moving: ``|v| >= min_ground_speed_mps`` and finite.
    """
    name = spec.motion_field
    if name is None:
        return None
    speed = np.abs(rows[name].astype(np.float64))
    return speed, np.isfinite(speed) & (speed >= min_ground_speed_mps)


def _flag_bits(rows: np.ndarray) -> np.ndarray:
    """The rows' ``flags`` as int64, zeros when the rows have none, shape (n,)."""
    if "flags" in (rows.dtype.names or ()):
        return rows["flags"].astype(np.int64)
    return np.zeros(rows.shape[0], dtype=np.int64)


def channel_slips(
    rows: np.ndarray, spec: EstimatorSpec
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Per slip channel of ``spec`` (its order): ``(slip_pct, valid)``, float64 and bool,
    shape (n,) each.

    ``valid``: the channel's ``valid_flag`` is set (no flag: every row) and its slip is finite.
    """
    flags = _flag_bits(rows)
    out = []
    for channel in spec.slips:
        slip = rows[channel.field].astype(np.float64)
        valid = np.isfinite(slip)
        if channel.valid_flag is not None:
            valid &= (flags & spec.flag_mask(channel.valid_flag)) != 0
        out.append((slip, valid))
    return tuple(out)


def degraded_rows(rows: np.ndarray, spec: EstimatorSpec) -> np.ndarray:
    """Whether each row has any of ``spec.degraded_flags`` set, bool, shape (n,)."""
    mask = 0
    for name in spec.degraded_flags:
        mask |= spec.flag_mask(name)
    return (_flag_bits(rows) & mask) != 0


def channel_edges(
    channel: SlipChannel, band_edges_pct: Sequence[float] | None
) -> tuple[float, ...]:
    """The band edges of ``channel``: ``band_edges_pct`` (the vehicle's) when given, else the
    channel's own."""
    return check_band_edges(channel.band_edges_pct if band_edges_pct is None else band_edges_pct)


def check_band_edges(band_edges_pct: Sequence[float]) -> tuple[float, ...]:
    """The band edges as floats; ValueError unless a non-empty increasing sequence."""
    edges = tuple(float(e) for e in band_edges_pct)
    if not edges or any(b <= a for a, b in pairwise(edges)):
        raise ValueError("band_edges_pct must be a non-empty increasing sequence")
    return edges


def band_index(abs_slip_pct: np.ndarray, edges: Sequence[float]) -> np.ndarray:
    """Band of each ``|slip|``, 0 … ``len(edges)`` (an edge belongs to the upper band).

    ``abs_slip_pct`` : shape (n,); returns intp, shape (n,).
    """
    return np.searchsorted(np.asarray(edges, dtype=np.float64), abs_slip_pct, side="right")


def band_bounds(edges: Sequence[float]) -> tuple[tuple[float, float | None], ...]:
    """``(lower_pct, upper_pct)`` of each band; the last has no upper edge (None)."""
    lowers = (0.0, *map(float, edges))
    uppers: tuple[float | None, ...] = (*map(float, edges), None)
    return tuple(zip(lowers, uppers, strict=True))


def band_label(lower_pct: float, upper_pct: float | None) -> str:
    """A band's name in table columns: ``0_5``, ``5_15``, ``15_up``."""
    lo = f"{lower_pct:g}"
    return f"{lo}_{upper_pct:g}" if upper_pct is not None else f"{lo}_up"


def _stat(values: np.ndarray, how: str) -> float | None:
    if values.size == 0:
        return None
    if how == "mean":
        return float(np.mean(values))
    if how == "median":
        return float(np.median(values))
    if how == "p95":
        return float(np.percentile(values, 95.0))
    if how == "min":
        return float(np.min(values))
    return float(np.max(values))


def _channel_stats(
    channel: SlipChannel,
    slip: np.ndarray,
    valid: np.ndarray,
    w_ns: np.ndarray,
    edges: tuple[float, ...],
) -> ChannelSlipStats:
    s = slip[valid]
    w = w_ns[valid]
    total_ns = int(w.sum())
    per_band = np.bincount(
        band_index(np.abs(s), edges), weights=w.astype(np.float64), minlength=len(edges) + 1
    )
    bands = tuple(
        SlipBand(
            lower_pct=lo,
            upper_pct=up,
            seconds=float(sec_ns) / _NS,
            share=float(sec_ns) / total_ns if total_ns > 0 else None,
        )
        for (lo, up), sec_ns in zip(band_bounds(edges), per_band, strict=True)
    )
    return ChannelSlipStats(
        label=channel.label,
        field=channel.field,
        band_edges_pct=edges,
        samples=int(s.size),
        valid_s=total_ns / _NS,
        mean_pct=_stat(s, "mean"),
        median_pct=_stat(s, "median"),
        p95_pct=_stat(s, "p95"),
        min_pct=_stat(s, "min"),
        max_pct=_stat(s, "max"),
        bands=bands,
    )


def _motion_stats(
    speed: np.ndarray, moving: np.ndarray, w_ns: np.ndarray
) -> tuple[float, float, SpeedStats]:
    """``(moving_s, distance_m, speed statistics)`` of the module docstring."""
    moving_ns = int(w_ns[moving].sum())
    distance_m = float(np.dot(speed[moving], w_ns[moving].astype(np.float64)) / _NS)
    moving_speed = speed[moving]
    stats = SpeedStats(
        mean_mps=distance_m / (moving_ns / _NS) if moving_ns > 0 else None,
        median_mps=_stat(moving_speed, "median"),
        p95_mps=_stat(moving_speed, "p95"),
        max_mps=_stat(speed[np.isfinite(speed)], "max"),
    )
    return moving_ns / _NS, distance_m, stats


_NO_SPEED = SpeedStats(None, None, None, None)


def _state_stats(
    rows: np.ndarray,
    spec: EstimatorSpec,
    channel: StateChannel,
    w_ns: np.ndarray,
    motion: tuple[np.ndarray, np.ndarray] | None,
) -> dict[str, StateStats]:
    """Time, distance and slip per state label (module docstring)."""
    state = rows[channel.field].astype(np.int64)
    slips = list(zip(spec.slips, channel_slips(rows, spec), strict=True))
    out = {}
    for value, label in ((sv.value, sv.name) for sv in channel.states):
        here = state == value
        if not here.any():
            continue
        distance = None
        if motion is not None:
            speed, moving = motion
            sel = here & moving
            distance = float(np.dot(speed[sel], w_ns[sel].astype(np.float64)) / _NS)
        out[label] = StateStats(
            label=label,
            seconds=int(w_ns[here].sum()) / _NS,
            distance_m=distance,
            slip_mean_pct={c.key: _stat(slip[here & ok], "mean") for c, (slip, ok) in slips},
            slip_p95_pct={c.key: _stat(slip[here & ok], "p95") for c, (slip, ok) in slips},
        )
    return out


def vehicle_report(
    rows: np.ndarray,
    spec: EstimatorSpec,
    *,
    start_ns: int,
    end_ns: int,
    band_edges_pct: Sequence[float] | None = None,
    min_ground_speed_mps: float = 0.2,
    max_gap_s: float = 1.0,
) -> VehicleReport:
    """Compute the report of one vehicle's estimator (definitions in the module docstring).

    Parameters
    ----------
    rows : ndarray, shape (n,), structured with at least :func:`report_fields` of ``spec``
        Estimates with ``start_ns <= stamp_ns < end_ns``, sorted by ``stamp_ns``.
    spec : the estimator whose rows these are.
    band_edges_pct : increasing edges of the slip bands, percent of ``|slip|``, for every slip
        channel (the vehicle's); None: each channel's own.
    min_ground_speed_mps : speed from which the vehicle counts as moving.
    max_gap_s : a step between rows longer than this is a data gap.
    """
    stamps = rows["stamp_ns"].astype(np.int64)
    w_ns = time_weights_ns(stamps, end_ns, round(max_gap_s * _NS))
    motion = motion_speed(rows, spec, min_ground_speed_mps)
    moving_s, distance_m, speed = None, None, _NO_SPEED
    if motion is not None:
        moving_s, distance_m, speed = _motion_stats(*motion, w_ns)
    slips = {
        channel.key: _channel_stats(
            channel, slip, valid, w_ns, channel_edges(channel, band_edges_pct)
        )
        for channel, (slip, valid) in zip(spec.slips, channel_slips(rows, spec), strict=True)
    }
    n = int(stamps.shape[0])
    states = {} if not spec.states else _state_stats(rows, spec, spec.states[0], w_ns, motion)
    return VehicleReport(
        start_ns=int(start_ns),
        end_ns=int(end_ns),
        rows=n,
        first_stamp_ns=int(stamps[0]) if n else None,
        last_stamp_ns=int(stamps[-1]) if n else None,
        covered_s=int(w_ns.sum()) / _NS,
        motion=spec.motion,
        motion_field=spec.motion_field,
        moving_s=moving_s,
        distance_m=distance_m,
        degraded_s=int(w_ns[degraded_rows(rows, spec)].sum()) / _NS,
        speed=speed,
        slips=slips,
        states=states,
    )


def flatten_report(
    vehicle_id: str, estimator: str, report: VehicleReport, counts: IngestCounts
) -> dict[str, Any]:
    """One flat table row (column name → scalar) of a vehicle's report, for fleet tables.

    Slip columns are named by the channel key, e.g. ``slip_left_mean_pct``; band columns by
    their edges, e.g. ``slip_left_share_5_15``. Vehicles with other channels or band edges get
    other columns (a fleet table takes the union).
    """
    row: dict[str, Any] = {
        "vehicle_id": vehicle_id,
        "estimator": estimator,
        "rows": report.rows,
        "first_stamp_ns": report.first_stamp_ns,
        "last_stamp_ns": report.last_stamp_ns,
        "covered_s": report.covered_s,
        "moving_s": report.moving_s,
        "distance_m": report.distance_m,
        "degraded_s": report.degraded_s,
        "speed_mean_mps": report.speed.mean_mps,
        "speed_median_mps": report.speed.median_mps,
        "speed_p95_mps": report.speed.p95_mps,
        "speed_max_mps": report.speed.max_mps,
    }
    for key, stats in report.slips.items():
        row.update(_slip_columns(key, stats))
    for label, st in report.states.items():
        row.update(_state_columns(label, st))
    row.update(_packet_columns(counts))
    return row


def _slip_columns(key: str, stats: ChannelSlipStats) -> dict[str, Any]:
    """The columns of slip channel ``key``: its statistics, then its band shares."""
    row: dict[str, Any] = {
        f"slip_{key}_samples": stats.samples,
        f"slip_{key}_mean_pct": stats.mean_pct,
        f"slip_{key}_median_pct": stats.median_pct,
        f"slip_{key}_p95_pct": stats.p95_pct,
        f"slip_{key}_min_pct": stats.min_pct,
        f"slip_{key}_max_pct": stats.max_pct,
    }
    for band in stats.bands:
        row[f"slip_{key}_share_{band_label(band.lower_pct, band.upper_pct)}"] = band.share
    return row


def _state_columns(label: str, st: StateStats) -> dict[str, Any]:
    """The columns of motion state ``label``: its time, distance and mean slip per channel."""
    row: dict[str, Any] = {
        f"state_{label}_s": st.seconds,
        f"state_{label}_distance_m": st.distance_m,
    }
    for key, mean in st.slip_mean_pct.items():
        row[f"state_{label}_slip_{key}_mean_pct"] = mean
    return row


def _packet_columns(counts: IngestCounts) -> dict[str, Any]:
    """The ingest counters' columns, then the rejections by reason."""
    row: dict[str, Any] = {
        "packets_received": counts.received,
        "packets_accepted": counts.accepted,
        "packets_rejected": counts.rejected,
        "packets_late": counts.late,
        "packets_duplicate": counts.duplicate,
        "packets_lost": counts.lost,
    }
    for reason, value in counts.rejected_by_reason.items():
        row[f"packets_rejected_{reason}"] = value
    return row
