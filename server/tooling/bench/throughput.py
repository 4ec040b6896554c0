"""Fleet throughput: how many vehicles one server (and a pair of shards) holds in real time.

``slipfleet bench throughput [--json PATH]`` or ``python -m server.tooling.bench.throughput``.

Three parts, all on loopback, in one run:

1. **Flood capacity** — separate publisher processes send pre-encoded simulated packets
   (``field_work``, ≈30 packets per vehicle-second of sensor time) for ``FLOOD_VEHICLES``
   vehicles as fast as Zenoh's BLOCK congestion control lets them, into

   * a bare Zenoh subscriber that only counts samples (the **raw receive rate**);
   * the **product** in this process: :class:`server.runtime.Runtime` (embedded router,
     decode, reorder, batched MDSF engine, SQLite writer) without HTTP;
   * a **naive baseline**: one thread that decodes every packet into pydantic models, keeps an
     :class:`estimator.mdsf.MdsfFilter` (filterpy) per vehicle stepped every
     ``MdsfConfig.tick_ns`` of sensor time, and commits its rows to SQLite once per 100 ms tick.

   Each reports packets/s; the table gives them as ratios and as "vehicle equivalents"
   (packets/s ÷ 30), and the CPU the product and the baseline spent (this process, all
   threads) per vehicle-second of sensor data. All three rates count packets handled, first
   to last (the product's pipeline estimates each vehicle up to its streams' watermarks as the
   packets come; what lies past a vehicle's lowest watermark at the end stays held).
   The baseline is lighter than the product's model (four observations, no wheel-edge
   speed tracking, no slip or pitch): it bounds what a plain per-vehicle loop costs.

2. **Ladder** — real-time simulated fleets (:func:`server.tooling.loadtest.run_loadtest`, scenario
   mix) of ``RUNGS`` vehicles against (a) one server, (b) two server processes that each
   own half the fleet by key expression (``zenoh.vehicle_filter`` ``a-$*`` / ``b-$*``), all
   clients of one router process (:mod:`server.tooling.router`) and writing to one PostgreSQL
   database (``$SLIPFLEET_TEST_PG_URL``, else a throwaway cluster from
   ``scripts/pg-test-cluster``). A rung *holds* when no packet is lost, late or missing, the
   server received ≥ 98 % of what was sent in the window and the p99 sensor→stored latency
   stays under the ladder's bound; each ladder stops at the first rung that does not hold.
   Three ladders, ``single``, ``pair`` and ``workers`` (one server whose decode, reorder and
   estimators run in two worker processes, ``ingest.workers = 2``, :mod:`server.ingest.workers`),
   otherwise with the default server settings (bound ``KEEP_UP_P99_MS``: the server keeps up).
   The ``floor`` column: 0 loss and p99 < 250 ms, the product target. ``--ladders`` picks
   some of them and ``--from N`` starts each at the first rung of at least ``N`` vehicles.

3. **Profile** — the single server at the ``PROFILE_VEHICLES`` rung is sampled with py-spy
   (when installed) and the heaviest frames are printed.

Numbers depend on the machine and whatever else runs on it; the ratios come from the same run.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import logging
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from server.tooling.shards import RouterProcess, shard_layout, sharded_servers

__all__ = ["run"]

#: Vehicles and packets per vehicle of the flood tests.
FLOOD_VEHICLES = 100
FLOOD_PACKETS = 300
FLOOD_PUBLISHERS = 2
#: Fleet sizes of the ladder.
RUNGS = (50, 100, 200, 300, 400, 500, 600, 800, 1000, 1200, 1600, 2400, 3200)
#: Measured seconds per rung (after the warm-up).
RUNG_WINDOW_S = 12.0
RUNG_WARMUP_S = 5.0
#: A rung whose p99 sensor→stored latency exceeds this is falling behind.
KEEP_UP_P99_MS = 2500.0
#: The product target: p99 sensor→stored latency with zero loss.
FLOOR_P99_MS = 250.0
#: A ladder stops starting rungs after this many seconds.
LADDER_BUDGET_S = 240.0
PROFILE_VEHICLES = 100
#: py-spy sampling of the profiled server: rate (Hz) and duration (s).
PROFILE_RATE_HZ = 100
PROFILE_S = 10
PACKETS_PER_VEHICLE_S = 30.0

_FLOOD = """
import json, sys, time, zenoh
from server.tooling.bench.throughput import flood_payloads
from server.ingest.zenoh_session import make_config
from server.protocol.keys import Stream, sensor_key
from server.settings import ZenohSettings
first, vehicles, n_packets, endpoint = (int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]),
                                        sys.argv[4])
enc = flood_payloads(n_packets)
with zenoh.open(make_config(ZenohSettings(connect=[endpoint]))) as session:
    pubs = {
        (v, s): session.declare_publisher(
            sensor_key("fleet", f"flood-{v:05d}", Stream(s)),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        for v in range(first, first + vehicles)
        for s in {s for s, _ in enc}
    }
    sys.stdin.readline()
    t = time.perf_counter()
    for s, payload in enc:
        for v in range(first, first + vehicles):
            pubs[(v, s)].put(payload)
    print(json.dumps({"publish_s": time.perf_counter() - t}), flush=True)
    time.sleep(1.0)
"""


def flood_payloads(n_packets: int) -> list[tuple[str, bytes]]:
    """``(stream, payload)`` of the first ``n_packets`` packets of a simulated ``field_work``
    run, sequence numbers per stream, stamps starting now (so the server's reorder windows and
    latency counters see fresh data)."""
    from estimator.sim import simulate
    from server.tooling.fleet_sim import encode_packets, packetize

    run = simulate("field_work", seed=1, start_ns=time.time_ns(), duration_s=60.0)
    return encode_packets(packetize(run.sent_in_arrival_order(), run.start_ns)[:n_packets])


@contextlib.contextmanager
def _flooders(endpoint: str, vehicles: int, packets: int) -> Iterator[list[subprocess.Popen[str]]]:
    per = -(-vehicles // FLOOD_PUBLISHERS)
    procs = []
    for k in range(FLOOD_PUBLISHERS):
        first, n = k * per, min(per, vehicles - k * per)
        if n <= 0:
            continue
        procs.append(
            subprocess.Popen(
                [sys.executable, "-c", _FLOOD, str(first), str(n), str(packets), endpoint],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
        )
    try:
        yield procs
    finally:
        for p in procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(30)
            if p.poll() is None:
                p.kill()
                p.wait(5)
            for stream in (p.stdin, p.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError, ValueError):
                        stream.close()


def _go(procs: Sequence[subprocess.Popen[str]], settle_s: float = 1.5) -> None:
    time.sleep(settle_s)  # publishers declared and matched
    for p in procs:
        assert p.stdin is not None
        p.stdin.write("go\n")
        p.stdin.flush()


def _wait_count(count: Any, total: int, timeout_s: float = 300.0) -> tuple[int, float]:
    """Poll ``count()`` until it reaches ``total``; (count, seconds from first to last)."""
    first: float | None = None
    last = time.perf_counter()
    deadline = time.monotonic() + timeout_s
    n = 0
    stalled_since = time.monotonic()
    prev = -1
    while n < total and time.monotonic() < deadline:
        n = count()
        now = time.perf_counter()
        if n and first is None:
            first = now
        if n != prev:
            prev, last, stalled_since = n, now, time.monotonic()
        elif time.monotonic() - stalled_since > 10.0:
            break  # nothing more is coming
        time.sleep(0.002)
    return n, last - (first or last)


def _endpoint() -> str:
    from server.tooling.ports import free_port

    return f"tcp/127.0.0.1:{free_port()}"


def flood_raw(vehicles: int = FLOOD_VEHICLES, packets: int = FLOOD_PACKETS) -> dict[str, Any]:
    """Packets/s a bare Zenoh subscriber (router mode, FIFO channel, count only) receives."""
    import zenoh

    from server.ingest.zenoh_session import make_config
    from server.settings import ZenohSettings

    endpoint = _endpoint()
    total = vehicles * packets
    received = 0
    with zenoh.open(make_config(ZenohSettings(listen=[endpoint]))) as session:
        sub = session.declare_subscriber("fleet/**", zenoh.handlers.FifoChannel(65536))
        done = threading.Event()

        def drain() -> None:
            nonlocal received
            while not done.is_set():
                s = sub.handler.try_recv()
                if s is None:
                    time.sleep(0.0005)
                    continue
                received += 1

        t = threading.Thread(target=drain, daemon=True)
        t.start()
        with _flooders(endpoint, vehicles, packets) as procs:
            _go(procs)
            n, dt = _wait_count(lambda: received, total)
        done.set()
        t.join(2)
        sub.undeclare()
    return {"what": "raw zenoh", "packets": total, "received": n, "packets_per_s": n / dt}


def flood_product(vehicles: int = FLOOD_VEHICLES, packets: int = FLOOD_PACKETS) -> dict[str, Any]:
    """Packets/s through the server runtime (decode, reorder, MDSF engine, SQLite writer)."""
    from server.runtime import Runtime
    from server.settings import Settings

    endpoint = _endpoint()
    total = vehicles * packets
    with tempfile.TemporaryDirectory(prefix="slipfleet-bench-") as tmp:
        settings = Settings.model_validate(
            {
                "zenoh": {"listen": [endpoint]},
                "storage": {"data_dir": tmp},
                "viewer": {"enabled": False},
            }
        )
        rt = Runtime(settings)
        rt.open()
        try:
            assert rt.pipeline is not None and rt.writer is not None
            pipe, writer = rt.pipeline, rt.writer

            def count() -> int:
                return sum(c["received"] for c in pipe.counters_snapshot().values())

            cpu0 = time.process_time()
            with _flooders(endpoint, vehicles, packets) as procs:
                _go(procs)
                # packets handled first to last, as for raw and naive: the pipeline counts a
                # packet when it takes it, and estimates each vehicle up to its streams'
                # watermarks as it goes
                n, dt = _wait_count(count, total)
                rows, t_last = pipe.stats()["rows"], time.perf_counter()
                while time.perf_counter() - t_last < 1.5:  # the last rows, for the row count
                    time.sleep(0.01)
                    now_rows = pipe.stats()["rows"]
                    if now_rows != rows:
                        rows, t_last = now_rows, time.perf_counter()
            cpu = time.process_time() - cpu0
            writer.flush(30.0)
            rows = writer.stats().rows_written
        finally:
            rt.close()
    return {
        "what": "product",
        "packets": total,
        "received": n,
        "packets_per_s": n / dt,
        "rows": rows,
        "cpu_s": cpu,
    }


class _NaiveLoop:
    """The naive baseline's per-packet work (see the module docstring): pydantic decode, one
    filterpy :class:`estimator.mdsf.MdsfFilter` per vehicle stepped every ``tick_ns`` of IMU
    time, rows committed to SQLite every 100 ms."""

    def __init__(self, db: sqlite3.Connection) -> None:
        import pydantic

        from estimator.mdsf import MdsfConfig

        class Gnss(pydantic.BaseModel):
            stamp_ns: int
            vel_enu_mps: list[float]
            heading_rad: float

        class Imu(pydantic.BaseModel):
            stamp_ns: list[int]
            accel_mps2: list[list[float]]
            gyro_radps: list[list[float]]

        class Edges(pydantic.BaseModel):
            wheel: int
            stamp_ns: list[int]

        class Wheels(pydantic.BaseModel):
            edges: list[Edges]

        self.models: dict[str, type[pydantic.BaseModel]] = {
            "gnss": Gnss,
            "imu": Imu,
            "wheels": Wheels,
        }
        self.config = MdsfConfig()
        self.db = db
        self.filters: dict[str, tuple[Any, list[int], dict[str, float]]] = {}
        self.pending: list[tuple[str, int, float, float, float]] = []
        self.processed = 0
        self.rows_written = 0

    def _entry(self, vid: str) -> tuple[Any, list[int], dict[str, float]]:
        import numpy as np

        from estimator.config import WheeledRearDriveConfig
        from estimator.mdsf import MdsfFilter

        entry = self.filters.get(vid)
        if entry is None:
            f = MdsfFilter(self.config, WheeledRearDriveConfig())
            f.initialize(np.zeros(self.config.n_state), np.eye(self.config.n_state))
            entry = self.filters[vid] = (f, [0], {"v": 0.0})
        return entry

    def handle(self, key_expr: str, payload: bytes) -> None:
        """Decode one packet and, for IMU packets, step the vehicle's filter per due tick."""
        import msgpack
        import numpy as np

        key = key_expr.split("/")
        vid, stream = key[1], key[-1]
        raw = msgpack.unpackb(payload)
        f, last, latest = self._entry(vid)
        if stream == "gnss":
            g: Any = self.models["gnss"].model_validate(raw)
            latest["v"] = float(np.hypot(g.vel_enu_mps[0], g.vel_enu_mps[1]))
        elif stream == "wheels":
            edges = [
                {"wheel": e["wheel"], "stamp_ns": np.frombuffer(e["stamp_ns"], "<i8").tolist()}
                for e in raw["edges"]
            ]
            self.models["wheels"].model_validate({"edges": edges})
        else:
            self._imu(vid, f, last, latest, raw)
        self.processed += 1

    def _imu(self, vid: str, f: Any, last: list[int], latest: dict[str, float], raw: Any) -> None:
        import numpy as np

        from estimator.mdsf import MdsfObs

        imu: Any = self.models["imu"].model_validate(
            {
                "stamp_ns": np.frombuffer(raw["stamp_ns"], "<i8").tolist(),
                "accel_mps2": np.frombuffer(raw["accel_mps2"], "<f8").reshape(-1, 3).tolist(),
                "gyro_radps": np.frombuffer(raw["gyro_radps"], "<f8").reshape(-1, 3).tolist(),
            }
        )
        n_obs = self.config.n_obs
        R = np.eye(n_obs) * 0.01
        z = np.zeros(n_obs)
        mask = np.zeros(n_obs, dtype=bool)
        for t_ns, acc, gyr in zip(imu.stamp_ns, imu.accel_mps2, imu.gyro_radps, strict=True):
            if last[0] == 0:
                last[0] = t_ns
            if t_ns - last[0] < self.config.tick_ns:
                continue
            last[0] = t_ns
            z[MdsfObs.VG] = latest["v"]
            z[MdsfObs.A1] = acc[1]
            z[MdsfObs.OMEGA_X] = gyr[0]
            z[MdsfObs.OMEGA_Z] = gyr[2]
            mask[:4] = True
            f.step(z, R, mask)
            out, _ = f.outputs()
            self.pending.append((vid, t_ns, float(out[0]), float(out[1]), float(out[2])))

    def commit(self) -> None:
        if self.pending:
            self.db.executemany("INSERT INTO est VALUES (?, ?, ?, ?, ?)", self.pending)
            self.db.commit()
            self.rows_written += len(self.pending)
            self.pending = []


def flood_naive(vehicles: int = FLOOD_VEHICLES, packets: int = FLOOD_PACKETS) -> dict[str, Any]:
    """Packets/s through the naive baseline (see the module docstring)."""
    import zenoh

    from server.ingest.zenoh_session import make_config
    from server.settings import ZenohSettings

    endpoint = _endpoint()
    total = vehicles * packets
    with tempfile.TemporaryDirectory(prefix="slipfleet-naive-") as tmp:
        db = sqlite3.connect(str(Path(tmp) / "naive.sqlite"), check_same_thread=False)
        db.execute("CREATE TABLE est (vehicle TEXT, stamp_ns INTEGER, v REAL, vl REAL, vr REAL)")
        loop = _NaiveLoop(db)
        with zenoh.open(make_config(ZenohSettings(listen=[endpoint]))) as session:
            sub = session.declare_subscriber("fleet/**", zenoh.handlers.FifoChannel(65536))
            done = threading.Event()

            def work() -> None:
                next_commit = time.monotonic() + 0.1
                while not done.is_set():
                    sample = sub.handler.try_recv()
                    if sample is None:
                        time.sleep(0.0005)
                    else:
                        loop.handle(str(sample.key_expr), sample.payload.to_bytes())
                    if time.monotonic() >= next_commit:
                        loop.commit()
                        next_commit = time.monotonic() + 0.1

            worker = threading.Thread(target=work, daemon=True)
            cpu0 = time.process_time()
            worker.start()
            with _flooders(endpoint, vehicles, packets) as procs:
                _go(procs)
                n, dt = _wait_count(lambda: loop.processed, total, timeout_s=600)
            cpu = time.process_time() - cpu0
            time.sleep(0.3)
            done.set()
            worker.join(5)
            sub.undeclare()
        db.close()
    return {
        "what": "naive",
        "packets": total,
        "received": n,
        "packets_per_s": n / dt,
        "rows": loop.rows_written,
        "cpu_s": cpu,
    }


# ---------------------------------------------------------------------------------- ladder


@contextlib.contextmanager
def postgres_admin_url() -> Iterator[str]:
    """``$SLIPFLEET_TEST_PG_URL``, or a throwaway cluster (scripts/pg-test-cluster) for the run."""
    given = os.environ.get("SLIPFLEET_TEST_PG_URL")
    if given:
        yield given
        return
    script = Path(__file__).resolve().parents[3] / "scripts" / "pg-test-cluster"
    cluster = Path(tempfile.mkdtemp(prefix="slipfleet-bench-pg-"))
    started = subprocess.run(
        [sys.executable, str(script), "start", "--dir", str(cluster)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    if started.returncode != 0:
        raise RuntimeError(f"could not start PostgreSQL: {started.stdout}{started.stderr}")
    try:
        yield started.stdout.strip().splitlines()[-1]
    finally:
        subprocess.run(
            [sys.executable, str(script), "stop", "--dir", str(cluster)],
            capture_output=True,
            timeout=120,
            check=False,
        )
        shutil.rmtree(cluster, ignore_errors=True)


@contextlib.contextmanager
def fresh_shards(
    admin_url: str, filters: Sequence[str], settings: dict[str, Any] | None = None
) -> Iterator[tuple[RouterProcess, list[Any]]]:
    """:func:`server.tooling.shards.sharded_servers` on a fresh database, dropped afterwards."""
    from server.tooling.pgadmin import create_database, drop_database

    name = f"slipfleet_bench_{uuid.uuid4().hex[:10]}"
    url = create_database(admin_url, name)
    try:
        with sharded_servers(url, filters, settings) as shards:
            yield shards
    finally:
        with contextlib.suppress(Exception):
            drop_database(admin_url, name)


SINGLE = dict(zip(("filters", "ids"), shard_layout(1), strict=True))
PAIR = dict(zip(("filters", "ids"), shard_layout(2), strict=True))
#: (name, layout). Both run the server defaults, which target low latency (reorder by stream
#: watermarks, estimators advanced every MDSF tick, commits at most every 0.02 s); a rung holds
#: while the server keeps up (p99 < KEEP_UP_P99_MS), and the ``floor`` column says whether it
#: also meets the product target (0 loss, p99 < FLOOR_P99_MS).
#: ``workers``: one server whose pipeline runs in two worker processes (``ingest.workers``).
WORKERS = {**SINGLE, "settings": {"ingest": {"workers": 2}}}
LADDERS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("single", SINGLE),
    ("pair", PAIR),
    ("workers", WORKERS),
)


def rung(
    admin_url: str,
    layout: dict[str, Any],
    vehicles: int,
    profile: Path | None = None,
) -> dict[str, Any]:
    """One ladder rung: fresh database, router, servers of ``layout``, a real-time fleet."""
    from server.tooling.loadtest import LoadSpec, Target, run_loadtest

    spec = LoadSpec(vehicles=vehicles, duration_s=RUNG_WINDOW_S, warmup_s=RUNG_WARMUP_S)
    with fresh_shards(admin_url, layout["filters"], layout.get("settings")) as (router, servers):
        target = Target(
            (router.endpoint,),
            tuple(s.api for s in servers),
            tuple(s.pid for s in servers),
            tuple(layout["ids"]),
        )
        prof: subprocess.Popen[bytes] | None = None
        if profile is not None and shutil.which("py-spy"):
            delay = RUNG_WARMUP_S + 8.0
            prof = subprocess.Popen(
                [
                    "sh",
                    "-c",
                    f"sleep {delay} && exec py-spy record -p {servers[0].pid} -d {PROFILE_S} "
                    f"-r {PROFILE_RATE_HZ} "
                    f"-f raw -o {profile} --nonblocking",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        r = run_loadtest(spec, target, progress=sys.stderr.isatty())
        if prof is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                prof.wait(60)
    lat = r["latency"].get("stored", {})
    p99 = float(lat.get("p99_ms", float("nan")))
    kept = r["packets_received_window"] >= 0.98 * r["packets_sent_window"]
    loss = r["packets_lost_by_seq_gap"] + r["packets_missing"] + r["packets_late"]
    r["holds"] = bool(loss == 0 and kept and p99 < KEEP_UP_P99_MS)
    r["floor_ok"] = bool(loss == 0 and kept and p99 < FLOOR_P99_MS)
    r["loss"] = loss
    return r


def ladder(
    admin_url: str,
    name: str,
    layout: dict[str, Any],
    budget_s: float,
    first: int = 0,
) -> list[dict[str, Any]]:
    """Rungs of ``RUNGS`` from ``first`` vehicles on, until one does not hold or the time
    budget is spent."""
    out = []
    t0 = time.monotonic()
    for n in (n for n in RUNGS if n >= first):
        if time.monotonic() - t0 > budget_s:
            print(f"  {name}: time budget spent before {n} vehicles", flush=True)
            break
        r = rung(admin_url, layout, n)
        r["layout"] = name
        out.append(r)
        print("  " + _row(r), flush=True)
        if not r["holds"]:
            break
    return out


def profile_summary(raw: Path, top: int = 15) -> list[tuple[str, float, float]]:
    """Per frame (py-spy raw output): inclusive share of all samples (%) and CPU cores
    (samples ÷ (rate × duration); py-spy records only threads that are running)."""
    incl: collections.Counter[str] = collections.Counter()
    total = 0
    for line in raw.read_text().splitlines():
        stack, _, n_text = line.rpartition(" ")
        if not n_text.isdigit():
            continue
        n = int(n_text)
        total += n
        for frame in set(stack.split(";")):
            if "(" in frame and "threading.py" not in frame:
                incl[frame] += n
    per_core = PROFILE_RATE_HZ * PROFILE_S
    return [(f, 100.0 * n / max(total, 1), n / per_core) for f, n in incl.most_common(top)]


_HEADER = (
    f"{'ladder':<9} {'vehicles':>8} {'pkts/s':>8} {'recv %':>7} {'loss':>5} {'p50 ms':>7} "
    f"{'p99 ms':>7} {'live p99':>8} {'CPU cores':>9} {'RSS MB':>7} {'rows/s':>7} {'holds':>6} "
    f"{'floor':>5}  busiest server thread (cores)"
)


def _row(r: dict[str, Any]) -> str:
    lat = r["latency"].get("stored", {})
    live = r["latency"].get("live", {})
    recv = 100.0 * r["packets_received_window"] / max(r["packets_sent_window"], 1)
    return (
        f"{r['layout']:<9} {r['spec']['vehicles']:>8} {r['packets_per_s']:>8.0f} {recv:>7.1f} "
        f"{r['loss']:>5} {lat.get('p50_ms', float('nan')):>7.0f} "
        f"{lat.get('p99_ms', float('nan')):>7.0f} {live.get('p99_ms', float('nan')):>8.0f} "
        f"{r['server_cpu_cores']:>9.2f} {r['server_rss_mb_peak']:>7.0f} "
        f"{r['storage_rows_per_s']:>7.0f} {'yes' if r['holds'] else 'NO':>6} "
        f"{'yes' if r['floor_ok'] else 'no':>5}  {_busiest(r)}"
    )


def _busiest(r: dict[str, Any]) -> str:
    """The rung's busiest server thread and its cores (``server_thread_cores``)."""
    threads = r.get("server_thread_cores") or {}
    if not threads:
        return "-"
    name, cores = next(iter(threads.items()))
    return f"{name} {cores:.2f}"


def _floods() -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """The three flood paths (raw Zenoh, the product, the naive loop) and their table."""
    print(
        f"flood capacity ({FLOOD_VEHICLES} vehicles × {FLOOD_PACKETS} packets, "
        f"{FLOOD_PUBLISHERS} publisher processes, {os.cpu_count()} CPUs)",
        flush=True,
    )
    raw = flood_raw()
    product = flood_product()
    naive = flood_naive()
    print(
        f"{'path':<10} {'packets/s':>10} {'vehicle-eq':>10} {'× naive':>8} {'of raw':>7} "
        f"{'CPU ms per vehicle-s':>21}"
    )
    vehicle_s = FLOOD_VEHICLES * FLOOD_PACKETS / PACKETS_PER_VEHICLE_S
    for r in (raw, product, naive):
        cpu = f"{1000.0 * r['cpu_s'] / vehicle_s:.2f}" if "cpu_s" in r else "-"
        print(
            f"{r['what']:<10} {r['packets_per_s']:>10.0f} "
            f"{r['packets_per_s'] / PACKETS_PER_VEHICLE_S:>10.0f} "
            f"{r['packets_per_s'] / naive['packets_per_s']:>8.2f} "
            f"{r['packets_per_s'] / raw['packets_per_s']:>7.3f} {cpu:>21}"
        )
    return raw, product, naive


def _ladders(
    admin: str, ladder_budget_s: float, ladders: Sequence[str] | None, first: int
) -> dict[str, list[dict[str, Any]]]:
    """The ladders picked (all by default), each climbed from ``first`` vehicles."""
    print(
        f"\nladder: real-time mix fleet, {RUNG_WINDOW_S:.0f} s per rung, PostgreSQL, "
        "router process; stored latency = sensor stamp → committed row"
    )
    print("  " + _HEADER, flush=True)
    return {
        name: ladder(admin, name, layout, ladder_budget_s, first)
        for name, layout in LADDERS
        if ladders is None or name in ladders
    }


def _profile(admin: str, prof_path: Path, results: dict[str, Any]) -> None:
    """One single-server rung under py-spy; its busiest frames into ``results["profile"]``."""
    print(f"\nprofile: single server at {PROFILE_VEHICLES} vehicles (py-spy, inclusive)")
    prof = rung(admin, SINGLE, PROFILE_VEHICLES, profile=prof_path)
    prof["layout"] = "single"
    if prof_path.exists():
        frames = profile_summary(prof_path)
        print(f"  {'samples':>7} {'cores':>6}  frame (inclusive)")
        for frame, pct, cores in frames:
            print(f"  {pct:6.1f}% {cores:6.2f}  {frame}")
        results["profile"] = {"vehicles": PROFILE_VEHICLES, "top": frames, "rung": prof}
    else:
        print("  py-spy not available (pip install py-spy)")


def _summary(
    picked: dict[str, list[dict[str, Any]]],
    raw: dict[str, Any],
    product: dict[str, Any],
    naive: dict[str, Any],
    t_start: float,
) -> dict[str, Any]:
    """The top rungs per ladder and the flood ratios, printed on one line."""

    def top(rows: list[dict[str, Any]], key: str) -> int:
        return max((r["spec"]["vehicles"] for r in rows if r[key]), default=0)

    summary: dict[str, Any] = {
        "holds_vehicles": {name: top(rows, "holds") for name, rows in picked.items()},
        "floor_vehicles": {name: top(rows, "floor_ok") for name, rows in picked.items()},
        "product_over_naive": product["packets_per_s"] / naive["packets_per_s"],
        "product_over_raw": product["packets_per_s"] / raw["packets_per_s"],
        "total_s": time.monotonic() - t_start,
    }
    print(
        f"\nsummary: top rung that holds {summary['holds_vehicles']}; 0 loss and p99 < "
        f"{FLOOR_P99_MS:.0f} ms at {summary['floor_vehicles']} vehicles; "
        f"product = {summary['product_over_naive']:.2f}× naive, "
        f"{summary['product_over_raw']:.3f}× raw Zenoh; {summary['total_s']:.0f} s"
    )
    return summary


def run(
    json_path: str | Path | None = None,
    *,
    ladder_budget_s: float = LADDER_BUDGET_S,
    ladders: Sequence[str] | None = None,
    first: int = 0,
) -> dict[str, Any]:
    """Run the benchmark; print the tables; write JSON to ``json_path`` if given."""
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per /metrics scrape
    t_start = time.monotonic()
    raw, product, naive = _floods()
    results: dict[str, Any] = {"flood": {"raw": raw, "product": product, "naive": naive}}

    with postgres_admin_url() as admin:
        prof_path = Path(tempfile.mkdtemp(prefix="slipfleet-prof-")) / "server.raw"
        picked = _ladders(admin, ladder_budget_s, ladders, first)
        results["ladder"] = picked
        _profile(admin, prof_path, results)
        shutil.rmtree(prof_path.parent, ignore_errors=True)

    results["summary"] = _summary(picked, raw, product, naive, t_start)
    if json_path is not None:
        Path(json_path).write_text(json.dumps(results, indent=2, default=str))
    return results


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m server.tooling.bench.throughput", description=__doc__
    )
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--ladders",
        type=lambda text: [n for n in text.split(",") if n],
        default=None,
        help=f"comma-separated, of {', '.join(name for name, _ in LADDERS)} (default: all)",
    )
    parser.add_argument("--from", dest="first", type=int, default=0, help="first rung, vehicles")
    args = parser.parse_args(argv)
    unknown = set(args.ladders or ()) - {name for name, _ in LADDERS}
    if unknown:
        parser.error(f"unknown ladders: {', '.join(sorted(unknown))}")
    run(json_path=args.json, ladders=args.ladders, first=args.first)


if __name__ == "__main__":
    main()
