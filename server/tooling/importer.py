"""``slipfleet import``: logs of other systems into the store, with their original timestamps.

::

    CSV / Parquet (importer_tables)  ─┐
    MCAP, ROS 1/2 bags (importer_bags) ┴▶ ImportedLog ─▶ wire packets (importer_log.packets_of)
        ─▶ Pipeline (no Zenoh: Pipeline.submit_raw) ─▶ reorder ─▶ estimators ─▶ StoreWriter

The packets are those a vehicle would publish, decoded, reordered and estimated by the
server's own :class:`~server.ingest.pipeline.Pipeline`, so an imported drive gets the estimates
the same drive gets over Zenoh. The import writes the configured store itself (SQLite file or
PostgreSQL URL) and needs no running server; a running one serves the imported rows as soon as
they are committed, but must not be receiving the same vehicle meanwhile.

The pipeline's wall clock is the log's own: its ``clock_skew`` bound (``ingest.max_past_s``)
is widened to the log's span, since a historical log lies wholly in the past.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimator.config import VehicleConfig, WheeledRearDriveConfig, vehicle_config_from_dict
from server.estimation.registry import EstimatorRegistry
from server.ingest.pipeline import SEQ_HIGH, Pipeline
from server.protocol.keys import Stream
from server.settings import Settings
from server.storage import open_store
from server.storage.base import Store
from server.storage.writer import StoreWriter
from server.timeparse import format_ns
from server.tooling.importer_bags import TopicChoice
from server.tooling.importer_log import ImportedLog, LogError, WirePacket, packets_of

__all__ = [
    "FORMATS",
    "ImportRequest",
    "ImportResult",
    "guess_format",
    "import_command",
    "import_log",
    "progress_bar",
    "read_log",
    "summary_lines",
]

#: Packets handed to the pipeline at once (the Zenoh subscriber's burst size).
BURST = 512
#: Margin of the pipeline's ``clock_skew`` bounds around the log's span.
CLOCK_MARGIN_S = 60.0


@dataclass(frozen=True, slots=True)
class ImportResult:
    """What an import did: packets fed, the server's counts of them, estimate rows made and
    how many of those the store did not hold yet (a log imported again adds none)."""

    packets: int
    counters: dict[str, int]
    rows: int
    new_rows: int = 0


def summary_lines(log: ImportedLog, packets: Sequence[WirePacket], vehicle_id: str) -> list[str]:
    """The dry run's report: per stream samples and packets, and the time span."""
    span = log.span_ns()
    if span is None:
        return [f"{vehicle_id}: the log holds no IMU, GNSS or wheel-speed sample"]
    per_stream: dict[str, int] = {}
    for p in packets:
        per_stream[p.stream.value] = per_stream.get(p.stream.value, 0) + 1
    lines = [
        f"{vehicle_id}: {len(packets)} packets from {format_ns(span[0])} to "
        f"{format_ns(span[1])} ({(span[1] - span[0]) / 1e9:.1f} s)"
    ]
    for stream, n in log.counts().items():
        lines.append(f"  {stream:<7} {n:>9} samples {per_stream.get(stream, 0):>8} packets")
    return lines


def _import_settings(settings: Settings, span: tuple[int, int]) -> Settings:
    """``settings`` with the ``clock_skew`` bounds covering the log (wall clock: its end)."""
    past_s = (span[1] - span[0]) / 1e9 + CLOCK_MARGIN_S
    ingest = settings.ingest.model_copy(update={"max_past_s": max(past_s, 1.0)})
    return settings.model_copy(update={"ingest": ingest})


def _vehicle_config(store: Store, vehicle_id: str, given: VehicleConfig | None) -> VehicleConfig:
    """The config the import runs: the one given (stored for the vehicle), else the stored
    one, else the default rear-drive config."""
    if given is not None:
        return given
    record = store.get_vehicle(vehicle_id)
    if record is not None:
        return vehicle_config_from_dict(record.config)
    return WheeledRearDriveConfig()


def _stored_rows(store: Store, vehicle_id: str, span: tuple[int, int]) -> int:
    """Estimate rows of every estimator the vehicle has rows of, stamped within ``span``."""
    start_ns, end_ns = span
    return sum(
        len(store.query_series(vehicle_id, start_ns, end_ns + 1, ["stamp_ns"], name))
        for name in store.estimators_with_rows(vehicle_id)
    )


def _first_seq(totals: dict[str, int]) -> dict[Stream, int]:
    """Sequence numbers that follow what the vehicle already sent (none: from 0)."""
    out: dict[Stream, int] = {}
    for name, value in totals.items():
        if name.startswith(SEQ_HIGH):
            try:
                out[Stream(name.removeprefix(SEQ_HIGH))] = int(value) + 1
            except ValueError:
                continue
    return out


def _feed(
    pipeline: Pipeline, packets: Sequence[WirePacket], progress: Callable[[int], None]
) -> None:
    for i in range(0, len(packets), BURST):
        burst = packets[i : i + BURST]
        pipeline.submit_raw([(p.key, p.payload) for p in burst])
        progress(len(burst))


def import_log(
    settings: Settings,
    vehicle_id: str,
    log: ImportedLog,
    *,
    config: VehicleConfig | None = None,
    batch: int = 10,
    progress: Callable[[int], None] = lambda n: None,
) -> ImportResult:
    """Feed ``log`` as ``vehicle_id``'s packets through the server's pipeline into the store
    of ``settings``; ``progress(n)`` after every ``n`` packets handed over.

    The vehicle is stored with ``config`` (else it keeps its stored config, else the default);
    its ENU anchor, ingest counters and sequence numbers go on from the stored ones.
    """
    span = log.span_ns()
    if span is None:
        return ImportResult(0, {}, 0)
    store = open_store(settings.storage)
    try:
        cfg = _vehicle_config(store, vehicle_id, config)
        store.upsert_vehicle(vehicle_id, cfg.to_dict(), time.time_ns())
        totals = store.get_counters(vehicle_id)
        anchor = store.get_anchors(vehicle_id).get(vehicle_id)
        packets = packets_of(
            log,
            vehicle_id,
            prefix=settings.zenoh.key_prefix,
            batch=batch,
            first_seq=_first_seq(totals),
        )
        before = _stored_rows(store, vehicle_id, span)
        result = _run(
            _import_settings(settings, span),
            store,
            vehicle_id,
            cfg,
            packets,
            totals,
            anchor,
            span[1],
            progress,
        )
        new_rows = _stored_rows(store, vehicle_id, span) - before
        return dataclasses.replace(result, new_rows=new_rows)
    finally:
        store.close()


def _run(
    settings: Settings,
    store: Store,
    vehicle_id: str,
    config: VehicleConfig,
    packets: Sequence[WirePacket],
    totals: dict[str, int],
    anchor: Any,
    end_ns: int,
    progress: Callable[[int], None],
) -> ImportResult:
    """The pipeline and writer over ``store``, fed ``packets``, stopped once all are stored."""
    writer = StoreWriter(store, settings.storage).start()
    pipeline = Pipeline(
        settings, None, EstimatorRegistry(), sinks=[writer], wall_clock_ns=lambda: end_ns
    )
    pipeline.register_vehicle(vehicle_id, config)
    pipeline.restore_counters(vehicle_id, totals)
    if anchor is not None:
        pipeline.restore_anchor(vehicle_id, anchor)
    before = int(pipeline.stats()["rows"])
    pipeline.start()
    try:
        _feed(pipeline, packets, progress)
    finally:
        pipeline.stop(timeout_s=600.0)
        counters = pipeline.counters_snapshot()
        writer.submit_counters(counters)
        writer.submit_anchors(pipeline.anchors_snapshot())
        writer.close()
    mine = counters.get(vehicle_id, {})
    gained = {k: int(v) - int(totals.get(k, 0)) for k, v in mine.items()}
    rows = int(pipeline.stats()["rows"]) - before
    return ImportResult(len(packets), gained, rows)


def progress_bar(total: int) -> Callable[[int], None]:
    """A packet counter on stderr when it is a terminal (nothing otherwise)."""
    from tqdm import tqdm

    bar = tqdm(total=total, unit="packet", file=sys.stderr, disable=None, leave=False)

    def step(n: int) -> None:
        bar.update(n)
        if bar.n >= total:
            bar.close()

    return step


#: The formats ``slipfleet import`` reads.
FORMATS = ("csv", "parquet", "mcap", "rosbag")


def guess_format(path: Path) -> str:
    """The format of ``path`` by its name: a ROS 2 bag is a directory, a ROS 1 bag ``.bag``."""
    suffix = path.suffix.lower()
    if path.is_dir() or suffix == ".bag":
        return "rosbag"
    by_suffix = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet", ".mcap": "mcap"}
    if suffix not in by_suffix:
        raise LogError(f"cannot tell the format of {path}: give --format {'|'.join(FORMATS)}")
    return by_suffix[suffix]


def read_log(path: Path, fmt: str, column_map: Path | None, topics: TopicChoice) -> ImportedLog:
    """The samples of the log at ``path`` in format ``fmt`` (LogError naming what is wrong)."""
    if fmt in ("csv", "parquet"):
        from server.tooling.importer_tables import ColumnMap, read_table

        return read_table(path, fmt, ColumnMap.load(column_map))
    from server.tooling.importer_bags import read_bag, read_mcap

    return read_mcap(path, topics) if fmt == "mcap" else read_bag(path, topics)


@dataclass(frozen=True)
class ImportRequest:
    """What ``slipfleet import`` was asked: the log, its format, the vehicle and how."""

    path: Path
    vehicle_id: str
    fmt: str | None = None
    dry_run: bool = False
    column_map: Path | None = None
    topics: TopicChoice = field(default_factory=TopicChoice)
    vehicle_config: Path | None = None
    batch: int = 10


def _config_file(path: Path | None) -> VehicleConfig | None:
    if path is None:
        return None
    import json

    from estimator.config import ConfigError

    try:
        return vehicle_config_from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, ConfigError) as exc:
        raise LogError(f"cannot use the vehicle config {path}: {exc}") from None


def _novelty(result: ImportResult) -> str:
    """``""`` when every estimate row is new to the store, else how many were already there."""
    if result.new_rows >= result.rows:
        return ""
    held = result.rows - result.new_rows
    return f", {result.new_rows} new: the store held {held} already (was this log imported before?)"


def import_command(settings: Settings, req: ImportRequest) -> int:
    """Read, check, summarise and (unless a dry run) import; errors are one line (SystemExit)."""
    try:
        fmt = req.fmt or guess_format(req.path)
        config = _config_file(req.vehicle_config)
        log = read_log(req.path, fmt, req.column_map, req.topics)
        packets = packets_of(log, req.vehicle_id, prefix=settings.zenoh.key_prefix, batch=req.batch)
    except LogError as exc:
        raise SystemExit(f"slipfleet import: {req.path}: {exc}") from None
    print("\n".join(summary_lines(log, packets, req.vehicle_id)))
    if req.dry_run or not packets:
        return 0
    result = import_log(
        settings,
        req.vehicle_id,
        log,
        config=config,
        batch=req.batch,
        progress=progress_bar(len(packets)),
    )
    c = result.counters
    print(
        f"imported {result.packets} packets of {req.vehicle_id}: {c.get('accepted', 0)} accepted, "
        f"{c.get('duplicate', 0)} duplicate, {c.get('late', 0)} late, "
        f"{c.get('rejected', 0)} rejected; {result.rows} estimate rows{_novelty(result)}"
    )
    return 0 if c.get("accepted", 0) == result.packets else 1
