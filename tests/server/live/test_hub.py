"""LiveHub: latest rows, decimated windows, status and async wake-ups per (vehicle, estimator),
on hand-made rows of two specs (MDSF and the reference speed)."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from typing import Any

import numpy as np
import pytest

from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC, ReferenceFlag
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from server.live.hub import LiveHub, TierSpec, live_fields, quality

S = 1_000_000_000  # ns per second
T0 = 1_700_000_000 * S


def rows(
    stamps_s: list[float], *, slip_left: list[float] | None = None, vg: float = 2.0
) -> np.ndarray:
    r = empty_estimates(len(stamps_s))
    r["stamp_ns"] = [T0 + round(t * S) for t in stamps_s]
    r["vg_mps"] = vg
    r["vl_mps"] = vg
    r["vr_mps"] = vg
    r["slip_left_pct"] = slip_left if slip_left is not None else 1.0
    r["slip_right_pct"] = 2.0
    r["east_m"] = stamps_s
    r["north_m"] = 0.0
    r["flags"] = int(EstimateFlag.GNSS_OK | EstimateFlag.SLIP_LEFT_VALID)
    return r


def ref_rows(stamps_s: list[float], *, speed: float = 1.5, no_wheel: bool = False) -> np.ndarray:
    """Reference-speed rows (its spec's dtype)."""
    r = REFERENCE_SPEED_SPEC.empty_rows(len(stamps_s))
    r["stamp_ns"] = [T0 + round(t * S) for t in stamps_s]
    r["speed_mps"] = speed
    r["rim_mps"] = speed + 0.1
    r["accel_bias_mps2"] = 0.02
    r["flags"] = int(ReferenceFlag.NO_WHEEL if no_wheel else ReferenceFlag.WHEEL_OK)
    return r


def ref_batch(*parts: tuple[str, np.ndarray]) -> EstimateBatch:
    return EstimateBatch.of(list(parts), REFERENCE_SPEED_SPEC)


class Clock:
    def __init__(self, t_ns: int) -> None:
        self.t_ns = t_ns

    def __call__(self) -> int:
        return self.t_ns


def test_latest_row_and_arrival_time_per_vehicle() -> None:
    clock = Clock(T0 + 10 * S)
    hub = LiveHub(clock_ns=clock)
    hub.on_estimates([("a", rows([1.0, 2.0])), ("b", rows([1.5], vg=5.0))])
    row, arrival = hub.latest("a")  # type: ignore[misc]
    assert int(row["stamp_ns"]) == T0 + 2 * S
    assert arrival == T0 + 10 * S
    row_b, _ = hub.latest("b")  # type: ignore[misc]
    assert float(row_b["vg_mps"]) == 5.0
    assert hub.latest("nobody") is None
    assert hub.vehicle_ids() == ["a", "b"]
    assert hub.version == 1


def test_late_rows_are_dropped_and_counted() -> None:
    hub = LiveHub(clock_ns=Clock(T0))
    hub.on_estimates([("a", rows([5.0, 6.0]))])
    hub.on_estimates([("a", rows([4.0, 6.0, 7.0]))])
    row, _ = hub.latest("a")  # type: ignore[misc]
    assert int(row["stamp_ns"]) == T0 + 7 * S
    assert hub.rows_dropped_late == 2
    assert hub.rows_in == 3


def test_fine_window_keeps_every_row_at_its_resolution() -> None:
    hub = LiveHub(clock_ns=Clock(T0), tiers=(TierSpec("f", 0.1, 10.0), TierSpec("c", 1.0, 100.0)))
    t = [i * 0.1 for i in range(50)]
    hub.on_estimates([("a", rows(t))])
    w = hub.window("a", 2.0)
    assert w is not None and w["tier"] == "f"
    # rows with stamp >= newest - 2 s: 4.9 - 2.0 = 2.9 .. 4.9 → 21 rows
    assert len(w["stamp_ns"]) == 21
    assert w["stamp_ns"][-1] == T0 + round(4.9 * S)
    assert w["vg_mps"] == [2.0] * 21


def test_coarse_tier_keeps_slip_peak_and_newest_values_per_bucket() -> None:
    hub = LiveHub(clock_ns=Clock(T0), tiers=(TierSpec("f", 0.1, 1.0), TierSpec("c", 1.0, 100.0)))
    t = [0.0, 0.25, 0.5, 0.75, 1.0, 1.5]
    slip = [1.0, -9.0, 3.0, 2.0, 4.0, 5.0]
    # fed one row per call, as a 50 Hz pipeline would, so buckets merge across calls
    for ti, si in zip(t, slip, strict=True):
        hub.on_estimates([("a", rows([ti], slip_left=[si]))])
    w = hub.window("a", 50.0)
    assert w is not None and w["tier"] == "c"
    assert w["stamp_ns"] == [T0 + round(0.75 * S), T0 + round(1.5 * S)]
    assert w["slip_left_pct"] == [-9.0, 5.0]  # peak magnitude, sign kept


def test_same_result_whether_rows_come_in_one_batch_or_many() -> None:
    tiers = (TierSpec("f", 0.2, 2.0), TierSpec("c", 1.0, 100.0))
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.01, 0.3, 200)).tolist()
    slip = rng.normal(0, 10, 200).tolist()
    one = LiveHub(clock_ns=Clock(T0), tiers=tiers)
    one.on_estimates([("a", rows(t, slip_left=slip)), ("b", rows(t[:50]))])
    many = LiveHub(clock_ns=Clock(T0), tiers=tiers)
    for i in range(0, 200, 7):
        batch = [("a", rows(t[i : i + 7], slip_left=slip[i : i + 7]))]
        if i < 50:
            batch.append(("b", rows(t[i : min(i + 7, 50)])))
        many.on_estimates(batch)
    for vid in ("a", "b"):
        for window in (1.5, 80.0):
            assert one.window(vid, window) == many.window(vid, window)


def test_ring_is_bounded_and_drops_the_oldest() -> None:
    hub = LiveHub(clock_ns=Clock(T0), tiers=(TierSpec("f", 1.0, 5.0),))
    hub.on_estimates([("a", rows([float(i) for i in range(100)]))])
    w = hub.window("a", 1000.0)
    assert w is not None
    assert len(w["stamp_ns"]) == 6  # capacity = span / bucket + 1
    assert w["stamp_ns"][-1] == T0 + 99 * S


def test_incremental_window_and_max_points() -> None:
    hub = LiveHub(clock_ns=Clock(T0), tiers=(TierSpec("f", 0.01, 100.0),))
    hub.on_estimates([("a", rows([i * 0.05 for i in range(1000)]))])
    since = T0 + 40 * S
    w = hub.window("a", 100.0, since_ns=since)
    assert w is not None and min(w["stamp_ns"]) >= since and len(w["stamp_ns"]) == 200
    d = hub.window("a", 100.0, max_points=100)
    assert d is not None and 50 <= len(d["stamp_ns"]) <= 101


def test_vehicles_beyond_initial_capacity() -> None:
    hub = LiveHub(clock_ns=Clock(T0), initial_slots=2)
    hub.on_estimates([(f"v{i}", rows([1.0, 2.0], vg=float(i))) for i in range(9)])
    ids, latest, _ = hub.latest_all("mdsf")
    assert ids == [f"v{i}" for i in range(9)]
    assert latest["vg_mps"].tolist() == [float(i) for i in range(9)]
    w = hub.window("v8", 10.0)
    assert w is not None and len(w["stamp_ns"]) == 2


def test_status_from_sensor_age_and_wall_age() -> None:
    clock = Clock(T0 + 100 * S)
    hub = LiveHub(clock_ns=clock, stale_after_s=2.0, offline_after_s=10.0)
    hub.on_estimates([("a", rows([100.0])), ("b", rows([95.0])), ("c", rows([80.0]))])
    assert hub.status("a") == "live"
    assert hub.status("b") == "stale"  # 5 s behind the fleet's newest sensor time
    assert hub.status("c") == "offline"
    clock.t_ns += 3 * S  # nothing new arrives for 3 s of wall time
    assert hub.status("a") == "stale"
    ov = hub.overview()
    assert ov["ids"] == ["a", "b", "c"]
    assert ov["status"] == ["stale", "stale", "offline"]
    assert ov["age_s"] == [3.0, 5.0, 20.0]
    assert ov["quality"] == ["ok", "ok", "ok"]
    assert ov["slip_pct"] == {"left": [1.0, 1.0, 1.0], "right": [2.0, 2.0, 2.0]}
    assert ov["speed_mps"] == [2.0, 2.0, 2.0]
    assert ov["estimator"] == ["mdsf"] * 3


def test_overview_turns_nan_into_null() -> None:
    hub = LiveHub(clock_ns=Clock(T0))
    r = rows([1.0], slip_left=[float("nan")])
    hub.on_estimates([("a", r)])
    assert hub.overview()["slip_pct"]["left"] == [None]


def test_quality_from_the_specs_ok_and_degraded_flags() -> None:
    ok, degraded = int(EstimateFlag.GNSS_OK), int(EstimateFlag.DEGRADED | EstimateFlag.GATED)
    assert quality(MDSF_SPEC, ok) == "ok"
    assert quality(MDSF_SPEC, degraded | ok) == "degraded"
    assert quality(MDSF_SPEC, 0) == "none"
    assert quality(REFERENCE_SPEED_SPEC, int(ReferenceFlag.WHEEL_OK)) == "ok"
    assert quality(REFERENCE_SPEED_SPEC, int(ReferenceFlag.NO_WHEEL)) == "degraded"


def test_live_fields_come_from_the_spec_channels() -> None:
    assert set(live_fields(MDSF_SPEC)) == {
        *MDSF_SPEC.charts[0].fields,
        *MDSF_SPEC.charts[1].fields,
        "east_m",
        "north_m",
        "up_m",
        "flags",
    }
    assert live_fields(REFERENCE_SPEED_SPEC) == (
        "speed_mps",
        "rim_mps",
        "accel_bias_mps2",
        "flags",
    )


def test_wait_newer_wakes_on_a_batch_from_another_thread() -> None:
    hub = LiveHub(clock_ns=Clock(T0))

    async def main() -> tuple[int, int]:
        v0 = hub.version
        timer = threading.Timer(0.05, lambda: hub.on_estimates([("a", rows([1.0]))]))
        timer.start()
        loop = asyncio.get_running_loop()
        t_start = loop.time()
        v1 = await hub.wait_newer(v0, timeout_s=5.0)
        timer.join()
        assert loop.time() - t_start < 2.0
        v2 = await hub.wait_newer(v1, timeout_s=0.05)  # times out, same version
        return v1, v2

    v1, v2 = asyncio.run(main())
    assert v1 == 1 and v2 == 1


def test_rejects_bad_settings() -> None:
    with pytest.raises(ValueError):
        LiveHub(stale_after_s=5.0, offline_after_s=2.0)
    with pytest.raises(ValueError):
        TierSpec("x", 0.0, 1.0)


# ---------------------------------------------------------------------- WebSocket routes


class _Served:
    """The live routes over ``hub`` under a real uvicorn on 127.0.0.1, with a JSON WS client."""

    def __init__(self, hub: LiveHub | None) -> None:
        import uvicorn
        from fastapi import FastAPI

        from server.api.routes import live as live_routes
        from tests.support import free_port

        app = FastAPI()
        if hub is not None:
            app.state.live_hub = hub
        app.include_router(live_routes.router, prefix="/api/v1")
        self.port = free_port()
        config = uvicorn.Config(
            app, host="127.0.0.1", port=self.port, log_level="warning", ws="websockets-sansio"
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> _Served:
        self.thread.start()
        for _ in range(400):
            if self.server.started:
                return self
            time.sleep(0.025)
        raise RuntimeError("uvicorn did not start")

    def __exit__(self, *_exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)

    def connect(self, path: str) -> Any:
        from websockets.sync.client import connect

        return connect(f"ws://127.0.0.1:{self.port}{path}", max_size=2**24, open_timeout=10)


def _recv(ws: Any) -> dict[str, Any]:
    msg: dict[str, Any] = json.loads(ws.recv(timeout=10))
    return msg


def test_fleet_socket_sends_the_overview() -> None:
    hub = LiveHub()
    hub.on_estimates([("a", rows([1.0], vg=3.0)), ("b", rows([1.0]))])
    with _Served(hub) as srv, srv.connect("/api/v1/live/fleet?interval_ms=250") as ws:
        msg = _recv(ws)
        assert msg["type"] == "fleet"
        assert msg["ids"] == ["a", "b"]
        assert msg["speed_mps"] == [3.0, 2.0]
        assert msg["slip_pct"] == {"left": [1.0, 1.0], "right": [2.0, 2.0]}
        assert set(msg) >= {"status", "age_s", "estimator", "quality", "sent_ns"}
        assert _recv(ws)["type"] == "fleet"  # and again at its interval


def _merge(cols: dict[str, list[Any]], msg: dict[str, Any]) -> dict[str, list[Any]]:
    keep = [i for i, t in enumerate(cols["stamp_ns"]) if t < msg["from_ns"]]
    return {k: [v[i] for i in keep] + msg["columns"][k] for k, v in cols.items()}


def test_vehicle_socket_snapshot_then_appends_that_merge_cleanly() -> None:
    hub = LiveHub(tiers=(TierSpec("f", 0.1, 60.0), TierSpec("c", 1.0, 1800.0)))
    hub.on_estimates([("a", rows([i * 0.05 for i in range(40)]))])
    with _Served(hub) as srv, srv.connect("/api/v1/live/vehicles/a?window_s=30") as ws:
        snap = _recv(ws)
        assert snap["type"] == "snapshot" and snap["tier"] == "f"
        cols = snap["columns"]
        assert snap["latest"]["stamp_ns"] == cols["stamp_ns"][-1] == T0 + round(1.95 * S)
        assert snap["estimator"] == "mdsf" and snap["estimators"] == ["mdsf"]
        assert snap["latest"]["flag_names"] == ["GNSS_OK", "SLIP_LEFT_VALID"]
        assert snap["latest"]["quality"] == "ok"
        assert set(cols) == {"stamp_ns", *live_fields(MDSF_SPEC)}
        # new rows in several batches, the first in the bucket the client already holds
        for k in range(3):
            hub.on_estimates([("a", rows([1.97 + k * 0.5 + i * 0.05 for i in range(10)]))])
            time.sleep(0.1)
        last = T0 + round((1.97 + 1.0 + 0.45) * S)
        while True:
            msg = _recv(ws)
            assert msg["type"] == "append"
            cols = _merge(cols, msg)
            if cols["stamp_ns"][-1] == last:
                break
        fresh = hub.window("a", 30.0)  # the client's copy equals a fresh window from the hub
        assert fresh is not None
        assert cols["stamp_ns"] == fresh["stamp_ns"]
        assert cols["slip_left_pct"] == fresh["slip_left_pct"]
        ws.send(json.dumps({"window_s": 600}))  # a new window: a new snapshot, coarse tier
        while (msg := _recv(ws))["type"] != "snapshot":
            pass
        assert msg["window_s"] == 600 and msg["tier"] == "c"


def test_vehicle_socket_waits_for_an_unknown_vehicle() -> None:
    hub = LiveHub()
    with _Served(hub) as srv, srv.connect("/api/v1/live/vehicles/x") as ws:
        msg = _recv(ws)
        assert (msg["type"], msg["vehicle_id"]) == ("waiting", "x")
        hub.on_estimates([("x", rows([1.0]))])
        while (msg := _recv(ws))["type"] == "waiting":
            pass
        assert msg["type"] == "snapshot"
        assert msg["columns"]["stamp_ns"] == [T0 + S]


def test_sockets_close_when_there_is_no_hub() -> None:
    from websockets.exceptions import ConnectionClosed

    with _Served(None) as srv, srv.connect("/api/v1/live/fleet") as ws:
        with pytest.raises(ConnectionClosed) as exc:
            ws.recv(timeout=10)
        assert exc.value.rcvd is not None and exc.value.rcvd.code == 1011


def test_forget_drops_a_vehicle_and_reuses_its_slot() -> None:
    hub = LiveHub(clock_ns=Clock(T0), tiers=(TierSpec("f", 0.1, 10.0),))
    hub.on_estimates([("a", rows([1.0, 2.0])), ("b", rows([1.0], vg=7.0))])
    assert hub.forget("a") is True
    assert hub.forget("a") is False
    assert hub.latest("a") is None and hub.window("a", 10.0) is None
    assert hub.vehicle_ids() == ["b"]
    assert hub.overview()["ids"] == ["b"]
    hub.on_estimates([("c", rows([3.0], vg=5.0))])  # takes a's slot, starts empty
    w = hub.window("c", 10.0)
    assert w is not None and w["stamp_ns"] == [T0 + 3 * S]
    assert sorted(hub.vehicle_ids()) == ["b", "c"]
    ids, latest, _ = hub.latest_all("mdsf")
    assert dict(zip(ids, latest["vg_mps"].tolist(), strict=True)) == {"b": 7.0, "c": 5.0}


# ---------------------------------------------------------------------- two estimators


def test_rows_of_two_estimators_are_kept_apart_per_vehicle() -> None:
    hub = LiveHub(clock_ns=Clock(T0 + 10 * S), tiers=(TierSpec("f", 0.1, 10.0),))
    hub.on_estimates(ref_batch(("a", ref_rows([1.0, 1.5], speed=3.0)), ("b", ref_rows([1.0]))))
    hub.on_estimates(EstimateBatch.of([("a", rows([1.2]))], MDSF_SPEC))
    # the first estimator that brought rows is the primary when nobody says otherwise
    assert hub.estimators("a") == ["reference_speed", "mdsf"]
    assert hub.estimators("b") == ["reference_speed"] and hub.estimators("x") == []
    ref, _ = hub.latest("a", "reference_speed")  # type: ignore[misc]
    assert ref.dtype == REFERENCE_SPEED_SPEC.dtype and float(ref["speed_mps"]) == 3.0
    mdsf, _ = hub.latest("a", "mdsf")  # type: ignore[misc]
    assert mdsf.dtype == MDSF_SPEC.dtype and int(mdsf["stamp_ns"]) == T0 + round(1.2 * S)
    assert hub.latest("b", "mdsf") is None
    w = hub.window("a", 5.0, estimator="reference_speed")
    assert w is not None and w["estimator"] == "reference_speed"
    assert set(w) == {
        "estimator",
        "tier",
        "bucket_s",
        "stamp_ns",
        *live_fields(REFERENCE_SPEED_SPEC),
    }
    assert w["speed_mps"] == [3.0, 3.0] and w["flags"] == [int(ReferenceFlag.WHEEL_OK)] * 2
    assert hub.window("a", 5.0, estimator="mdsf")["slip_right_pct"] == [2.0]  # type: ignore[index]
    ids, latest, _ = hub.latest_all("reference_speed")
    assert ids == ["a", "b"] and latest.dtype == REFERENCE_SPEED_SPEC.dtype
    assert hub.forget("a") and hub.latest("a", "mdsf") is None
    assert hub.latest_all("mdsf")[0] == [] and hub.vehicle_ids() == ["b"]


def test_primary_of_decides_what_the_fleet_overview_shows() -> None:
    primaries = {"a": "mdsf", "b": "reference_speed", "c": "mdsf"}
    hub = LiveHub(clock_ns=Clock(T0 + 2 * S), primary_of=primaries.get)
    hub.on_estimates(ref_batch(("a", ref_rows([1.0])), ("b", ref_rows([1.0], no_wheel=True))))
    hub.on_estimates([("a", rows([1.0], vg=4.0)), ("c", rows([1.0], slip_left=[-7.0]))])
    assert hub.estimators("a") == ["mdsf", "reference_speed"]
    assert hub.primary("b") == "reference_speed"
    ov = hub.overview()
    assert ov["ids"] == ["a", "b", "c"]
    assert ov["estimator"] == ["mdsf", "reference_speed", "mdsf"]
    assert ov["speed_mps"] == [4.0, 1.5, 2.0]
    assert ov["slip_pct"] == {"left": [1.0, None, -7.0], "right": [2.0, None, 2.0]}
    assert ov["quality"] == ["ok", "degraded", "ok"]
    assert ov["flags"][1] == int(ReferenceFlag.NO_WHEEL)
    assert hub.latest_all("mdsf", primary_only=True)[0] == ["a", "c"]
    # a primary without rows here (yet) falls back to the first estimator with rows
    primaries["b"] = "mdsf"
    assert hub.primary("b") == "reference_speed"


def test_late_rows_are_counted_per_estimator() -> None:
    hub = LiveHub(clock_ns=Clock(T0))
    hub.on_estimates(ref_batch(("a", ref_rows([5.0]))))
    hub.on_estimates([("a", rows([3.0]))])  # older than the other estimator's row: not late
    hub.on_estimates(ref_batch(("a", ref_rows([4.0, 6.0]))))
    assert hub.rows_dropped_late == 1 and hub.rows_in == 3


def test_plain_rows_of_no_catalog_dtype_are_refused() -> None:
    hub = LiveHub()
    with pytest.raises(TypeError, match="EstimateBatch"):
        hub.on_estimates([("a", np.zeros(2, dtype=[("stamp_ns", "i8"), ("x_m", "f8")]))])


def test_vehicle_socket_per_estimator() -> None:
    hub = LiveHub(primary_of={"a": "mdsf"}.get)
    hub.on_estimates([("a", rows([1.0, 1.05]))])
    hub.on_estimates(ref_batch(("a", ref_rows([1.0, 1.05], speed=2.5))))
    with _Served(hub) as srv:
        with srv.connect("/api/v1/live/vehicles/a?estimator=reference_speed") as ws:
            snap = _recv(ws)
            assert snap["type"] == "snapshot" and snap["estimator"] == "reference_speed"
            assert snap["estimators"] == ["mdsf", "reference_speed"]
            assert set(snap["columns"]) == {"stamp_ns", *live_fields(REFERENCE_SPEED_SPEC)}
            assert snap["columns"]["speed_mps"] == [2.5, 2.5]
            latest = snap["latest"]
            assert set(latest) >= set(REFERENCE_SPEED_SPEC.field_names)
            assert latest["flag_names"] == ["WHEEL_OK"] and latest["quality"] == "ok"
            hub.on_estimates(ref_batch(("a", ref_rows([1.1], speed=2.75))))
            while (msg := _recv(ws))["columns"]["stamp_ns"][-1:] != [T0 + round(1.1 * S)]:
                pass
            assert msg["type"] == "append" and msg["estimator"] == "reference_speed"
            assert msg["columns"]["speed_mps"][-1] == 2.75
        with srv.connect("/api/v1/live/vehicles/a") as ws:  # default: the primary
            snap = _recv(ws)
            assert snap["estimator"] == "mdsf" and "slip_left_pct" in snap["columns"]
        with srv.connect("/api/v1/live/vehicles/a?estimator=other") as ws:
            msg = _recv(ws)
            assert (msg["type"], msg["estimator"]) == ("waiting", "other")
