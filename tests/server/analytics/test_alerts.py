"""AlertEngine on hand-made rows: slip held past the hold time, GNSS degraded, stale vehicles."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest

from estimator.config import SlipConfig
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import EstimatorSpec, FieldSpec, SlipChannel, WheelPosition
from estimator.types import EstimateBatch, EstimateFlag, empty_estimates
from server.analytics.alerts import SYSTEM, AlertEngine, AlertKind

SLIP_LEFT = "slip:mdsf:left"
SLIP_RIGHT = "slip:mdsf:right"
GNSS_DEGRADED = "flag:mdsf:DEGRADED"

S = 1_000_000_000
T0 = 1_700_000_000 * S
OK = int(EstimateFlag.GNSS_OK)
DEG = int(EstimateFlag.DEGRADED)


def rows(
    t_s: list[float], sl: list[float], sr: float = 0.0, flags: int | list[int] = OK
) -> np.ndarray:
    r = empty_estimates(len(t_s))
    r["stamp_ns"] = [T0 + round(t * S) for t in t_s]
    r["slip_left_pct"] = sl
    r["slip_right_pct"] = sr
    r["flags"] = flags
    return r


def mdsf(pairs: list[tuple[str, np.ndarray]]) -> EstimateBatch:
    return EstimateBatch.of(pairs, MDSF_SPEC)


class Clock:
    def __init__(self) -> None:
        self.t_ns = T0

    def __call__(self) -> int:
        return self.t_ns


def engine(**kw: Any) -> tuple[AlertEngine, list[tuple[str, dict[str, Any]]], Clock]:
    published: list[tuple[str, dict[str, Any]]] = []
    clock = Clock()
    cfg = SlipConfig(alert_threshold_pct=15.0, alert_hold_s=5.0)
    eng = AlertEngine(
        slip_config_for=lambda _v: cfg,
        publish=lambda v, e: published.append((v, e)),
        clock_ns=clock,
        **kw,
    )
    return eng, published, clock


def test_slip_alert_opens_after_hold_and_closes_when_slip_drops() -> None:
    eng, pub, _ = engine()
    t = [float(i) for i in range(12)]
    sl = [1, 20, 25, -30, 20, 20, 20, 22, 3, 20, 20, 1]
    for ti, si in zip(t, sl, strict=True):  # one row per batch
        eng.on_estimates(mdsf([("a", rows([ti], [si]))]))
    assert [e["event"] for _, e in pub] == ["open", "close"]
    closed = eng.alerts(state="closed")
    assert len(closed) == 1
    a = closed[0]
    assert a.kind == SLIP_LEFT
    assert a.start_ns == T0 + 1 * S  # where slip went above 15 %
    assert a.end_ns == T0 + 8 * S  # first row back below
    assert a.peak == 30.0 and a.threshold == 15.0
    # held 5 s at t=6: the open event is published then, with start at t=1
    assert pub[0][1]["start_ns"] == T0 + S and pub[0][1]["end_ns"] is None
    # 9..10 above for only 1 s: no alert
    assert eng.alerts(state="open") == []


def test_same_alerts_in_one_batch_as_in_many() -> None:
    t = [i * 0.5 for i in range(40)]
    sl = [20.0 if 4 <= i < 30 else 0.0 for i in range(40)]
    one, _, _ = engine()
    one.on_estimates(mdsf([("a", rows(t, sl, sr=0.0)), ("b", rows(t, [0.0] * 40, sr=-18.0))]))
    many, _, _ = engine()
    for i in range(0, 40, 3):
        many.on_estimates(
            mdsf(
                [
                    ("b", rows(t[i : i + 3], [0.0] * len(t[i : i + 3]), sr=-18.0)),
                    ("a", rows(t[i : i + 3], sl[i : i + 3])),
                ]
            )
        )

    def key(eng: AlertEngine) -> list[tuple[str, str, int, int | None, float | None]]:
        return sorted((a.vehicle_id, a.kind, a.start_ns, a.end_ns, a.peak) for a in eng.alerts())

    assert key(one) == key(many)
    assert key(one) == [
        ("a", SLIP_LEFT, T0 + 2 * S, T0 + 15 * S, 20.0),
        ("b", SLIP_RIGHT, T0, None, 18.0),
    ]


def test_nan_slip_breaks_the_run() -> None:
    eng, pub, _ = engine()
    t = [float(i) for i in range(8)]
    sl = [20, 20, 20, float("nan"), 20, 20, 20, 20]
    eng.on_estimates(mdsf([("a", rows(t, sl))]))
    assert pub == []


def test_per_vehicle_threshold_and_later_change() -> None:
    eng, _, _ = engine()
    eng.set_slip_config("gentle", SlipConfig(alert_threshold_pct=5.0, alert_hold_s=1.0))
    t = [float(i) for i in range(4)]
    eng.on_estimates(mdsf([("gentle", rows(t, [8.0] * 4)), ("std", rows(t, [8.0] * 4))]))
    assert [(a.vehicle_id, a.kind) for a in eng.alerts(state="open")] == [("gentle", SLIP_LEFT)]


def test_gnss_degraded_alert() -> None:
    eng, pub, _ = engine(flag_hold_s=1.0)
    t = [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    flags = [OK, DEG, DEG, DEG, OK, OK]
    eng.on_estimates(mdsf([("a", rows(t, [0.0] * 6, flags=flags))]))
    [a] = eng.alerts()
    assert a.kind == GNSS_DEGRADED
    assert (a.start_ns, a.end_ns) == (T0 + S // 2, T0 + 2 * S)
    assert [e["event"] for _, e in pub] == ["open", "close"]


def test_stale_opens_on_silence_and_closes_on_new_data() -> None:
    eng, pub, clock = engine(stale_after_s=10.0)
    eng.on_estimates(mdsf([("a", rows([0.0], [0.0])), ("b", rows([0.0], [0.0]))]))
    clock.t_ns += 5 * S
    eng.on_estimates(mdsf([("b", rows([5.0], [0.0]))]))
    clock.t_ns += 6 * S  # a silent 11 s, b 6 s
    opened = eng.check_stale()
    assert [(a.vehicle_id, a.kind) for a in opened] == [("a", AlertKind.STALE)]
    assert eng.check_stale() == []  # already open
    assert opened[0].start_ns == T0
    eng.on_estimates(mdsf([("a", rows([11.0], [0.0]))]))
    [closed] = eng.alerts(state="closed")
    assert closed.end_ns == T0 + 11 * S
    assert [(v, e["event"], e["kind"]) for v, e in pub] == [
        ("a", "open", "stale"),
        ("a", "close", "stale"),
    ]


def test_a_vehicle_without_rows_is_not_stale_from_the_epoch() -> None:
    eng, pub, clock = engine(stale_after_s=10.0)
    eng.set_slip_config("new", SlipConfig())  # what the runtime does when a vehicle joins
    clock.t_ns += 60 * S
    assert eng.check_stale() == []
    assert pub == []
    eng.on_estimates(mdsf([("new", rows([60.0], [0.0]))]))
    clock.t_ns += 11 * S
    [opened] = eng.check_stale()
    assert (opened.vehicle_id, opened.start_ns) == ("new", T0 + 60 * S)
    assert [(v, e["event"], e["start_ns"]) for v, e in pub] == [("new", "open", T0 + 60 * S)]
    # a slot freed by a forgotten vehicle and taken by a new one starts without rows again
    assert eng.forget("new")
    eng.set_slip_config("newer", SlipConfig())
    clock.t_ns += 60 * S
    assert eng.check_stale() == []


def test_publish_errors_are_counted_not_raised() -> None:
    def boom(_v: str, _e: dict[str, Any]) -> None:
        raise RuntimeError("bus down")

    eng = AlertEngine(publish=boom, slip_config_for=lambda _v: SlipConfig(alert_hold_s=1.0))
    eng.on_estimates(mdsf([("a", rows([0.0, 1.0, 2.0], [50.0, 50.0, 50.0]))]))
    assert eng.publish_errors == 1
    assert eng.open_count() == 1


def test_many_vehicles_grow_state() -> None:
    eng, _, _ = engine()
    eng.on_estimates(mdsf([(f"v{i}", rows([0.0, 6.0], [30.0, 30.0])) for i in range(100)]))
    assert eng.open_count() == 100
    assert len(eng.alerts(limit=10)) == 10
    assert {a.vehicle_id for a in eng.alerts(vehicle_id="v42")} == {"v42"}
    with pytest.raises(ValueError):
        eng.alerts(state="maybe")


def test_stale_thread_starts_and_stops() -> None:
    eng = AlertEngine(stale_after_s=0.01)
    eng.on_estimates(mdsf([("a", rows([0.0], [0.0]))]))
    eng.start(interval_s=0.01)
    try:
        for _ in range(200):
            if eng.open_count():
                break
            import time

            time.sleep(0.01)
    finally:
        eng.stop()
    assert [a.kind for a in eng.alerts()] == [AlertKind.STALE]


def _get_alerts(eng: AlertEngine | None, query: str) -> tuple[int, Any]:
    import asyncio

    import httpx
    from fastapi import FastAPI

    from server.api.errors import install_error_handlers
    from server.api.routes import alerts as alerts_routes

    app = FastAPI()
    install_error_handlers(app)
    if eng is not None:
        app.state.alert_engine = eng
    app.include_router(alerts_routes.router, prefix="/api/v1")

    async def go() -> tuple[int, Any]:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            resp = await client.get("/api/v1/alerts" + query)
            return resp.status_code, resp.json()

    return asyncio.run(go())


def test_alerts_route_lists_and_filters() -> None:
    eng, _, _ = engine()
    eng.on_estimates(
        mdsf(
            [
                ("a", rows([0.0, 6.0, 7.0], [30.0, 30.0, 0.0])),
                ("b", rows([0.0, 6.0], [0.0, 40.0], sr=40.0)),
            ]
        )
    )
    status, body = _get_alerts(eng, "")
    assert status == 200
    assert body["open_count"] == 1
    assert [(a["vehicle_id"], a["kind"], a["open"]) for a in body["alerts"]] == [
        ("b", SLIP_RIGHT, True),
        ("a", SLIP_LEFT, False),
    ]
    assert body["alerts"][1]["start_ns"] == T0 and body["alerts"][1]["end_ns"] == T0 + 7 * S
    assert (body["alerts"][0]["estimator"], body["alerts"][0]["channel"]) == ("mdsf", "right")
    eng.on_estimates(mdsf([("b", rows([7.0, 12.0], [40.0, 40.0], sr=40.0))]))
    status, body = _get_alerts(eng, "?state=open&vehicle_id=b")
    assert status == 200
    assert sorted(a["kind"] for a in body["alerts"]) == [SLIP_LEFT, SLIP_RIGHT]
    assert body["open_count"] == 2
    status, body = _get_alerts(eng, "?state=sometimes")
    assert status == 422


def test_alerts_route_without_engine_is_unavailable() -> None:
    status, body = _get_alerts(None, "")
    assert status == 503 and body["error"] == "unavailable"


@pytest.mark.parametrize("seed", range(5))
def test_random_chunking_does_not_change_the_alerts(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 120
    t = np.cumsum(rng.uniform(0.2, 0.8, n)).tolist()
    feeds = {}
    for v in ("a", "b", "c"):
        sl = np.where(rng.random(n) < 0.7, rng.uniform(16, 40, n), rng.uniform(0, 10, n))
        sl[rng.random(n) < 0.05] = np.nan
        sr = rng.uniform(-30, 30, n)
        flags = np.where(rng.random(n) < 0.3, DEG, OK)
        feeds[v] = rows(t, sl.tolist(), sr=0.0, flags=flags.tolist())
        feeds[v]["slip_right_pct"] = sr

    def run(cuts: list[int]) -> list[tuple[str, str, int, int | None, float | None]]:
        eng = AlertEngine(flag_hold_s=1.0)
        edges = [0, *cuts, n]
        for lo, hi in itertools.pairwise(edges):
            eng.on_estimates(mdsf([(v, r[lo:hi]) for v, r in feeds.items()]))
        return sorted(
            (a.vehicle_id, a.kind, a.start_ns, a.end_ns, a.peak) for a in eng.alerts(limit=5000)
        )

    whole = run([])
    assert whole, "the random feed raised no alert"
    assert run(list(range(1, n))) == whole
    assert run(sorted(rng.choice(np.arange(1, n), 15, replace=False).tolist())) == whole


def test_forget_closes_open_alerts_and_stops_stale_checks() -> None:
    eng, pub, clock = engine(stale_after_s=10.0)
    eng.on_estimates(mdsf([("a", rows([0.0, 6.0], [30.0, 30.0])), ("b", rows([0.0], [0.0]))]))
    assert eng.open_count() == 1
    assert eng.forget("a") is True
    assert eng.forget("a") is False
    assert eng.open_count() == 0
    [closed] = eng.alerts(state="closed")
    assert (closed.vehicle_id, closed.end_ns) == ("a", T0 + 6 * S)
    assert [e["event"] for _, e in pub] == ["open", "close"]
    clock.t_ns += 20 * S
    assert [a.vehicle_id for a in eng.check_stale()] == ["b"]  # not the forgotten one
    eng.on_estimates(mdsf([("c", rows([30.0], [0.0]))]))  # reuses the slot with a clean state
    assert eng.open_count() == 1  # b's stale alert only


def test_system_condition_opens_once_and_closes() -> None:
    events: list[tuple[str, dict[str, object]]] = []
    engine = AlertEngine(publish=lambda vid, ev: events.append((vid, ev)))
    opened = engine.set_system_condition(AlertKind.STORAGE_DOWN, True, now_ns=1_000)
    assert opened is not None and opened.vehicle_id == SYSTEM and opened.is_open
    assert engine.set_system_condition(AlertKind.STORAGE_DOWN, True, now_ns=2_000) is None
    assert engine.open_count() == 1
    assert engine.set_system_condition(AlertKind.ZENOH_DOWN, False, now_ns=2_000) is None
    closed = engine.set_system_condition(AlertKind.STORAGE_DOWN, False, now_ns=5_000)
    assert closed is not None and closed.id == opened.id and closed.end_ns == 5_000
    assert engine.open_count() == 0
    assert [(vid, ev["event"], ev["kind"]) for vid, ev in events] == [
        (SYSTEM, "open", "storage_down"),
        (SYSTEM, "close", "storage_down"),
    ]
    assert [a.kind for a in engine.alerts(state="closed")] == [AlertKind.STORAGE_DOWN]


def ref_rows(t_s: list[float], no_wheel: list[bool]) -> EstimateBatch:
    """Reference-speed rows of vehicle ``a``: NO_WHEEL where asked, WHEEL_OK elsewhere."""
    r = REFERENCE_SPEED_SPEC.empty_rows(len(t_s))
    r["stamp_ns"] = [T0 + round(t * S) for t in t_s]
    r["speed_mps"] = 2.0
    lost, ok = (
        REFERENCE_SPEED_SPEC.flag_mask("NO_WHEEL"),
        REFERENCE_SPEED_SPEC.flag_mask("WHEEL_OK"),
    )
    r["flags"] = [lost if n else ok for n in no_wheel]
    return EstimateBatch.of([("a", r)], REFERENCE_SPEED_SPEC)


def test_rules_of_each_estimator_are_its_own() -> None:
    """One vehicle, two estimators: MDSF's slip rule and the reference speed's flag rule open
    and close apart; the reference speed has no slip rule (no slip channel)."""
    eng, pub, _ = engine(flag_hold_s=1.0)
    t = [0.0, 1.0, 2.0, 3.0, 4.0]
    eng.on_estimates(ref_rows(t, [False, True, True, True, False]))
    eng.on_estimates(mdsf([("a", rows([*t, 5.0, 6.0], [30.0] * 7))]))
    kinds = [(e["event"], e["kind"], e["estimator"], e["channel"]) for _, e in pub]
    assert kinds == [
        ("open", "flag:reference_speed:NO_WHEEL", "reference_speed", "NO_WHEEL"),
        ("close", "flag:reference_speed:NO_WHEEL", "reference_speed", "NO_WHEEL"),
        ("open", SLIP_LEFT, "mdsf", "left"),
    ]
    [flag] = eng.alerts(state="closed")
    assert (flag.start_ns, flag.end_ns) == (T0 + S, T0 + 4 * S)
    assert flag.threshold is None and flag.peak is None
    [slip] = eng.alerts(state="open")
    assert slip.to_dict()["estimator"] == "mdsf" and slip.peak == 30.0
    # forgetting the vehicle closes what is open of every estimator
    eng.on_estimates(ref_rows([7.0, 8.0, 9.0], [True, True, True]))
    assert eng.open_count() == 2
    assert eng.forget("a") and eng.open_count() == 0


TRACKS = EstimatorSpec(
    name="tracks",
    title="track slip",
    kinds=("tracked",),
    inputs=("imu",),
    fields=(
        FieldSpec("stamp_ns", "i8", "ns", "time"),
        FieldSpec("left_pct", "f8", "%", "left track slip"),
        FieldSpec("right_pct", "f8", "%", "right track slip"),
    ),
    slips=(
        SlipChannel("lt", "left track", "left_pct", WheelPosition.TRACK_LEFT),
        SlipChannel("rt", "right track", "right_pct", WheelPosition.TRACK_RIGHT),
    ),
)


def test_slip_rule_per_channel_of_a_spec_without_flags() -> None:
    eng, pub, _ = engine()
    r = TRACKS.empty_rows(8)
    r["stamp_ns"] = T0 + np.arange(8) * S
    r["left_pct"] = 1.0
    r["right_pct"] = [20, 20, 25, 20, 20, 20, 2, 2]
    eng.on_estimates(EstimateBatch.of([("crawler", r)], TRACKS))
    assert [(e["event"], e["kind"], e["channel"]) for _, e in pub] == [
        ("open", "slip:tracks:rt", "rt"),
        ("close", "slip:tracks:rt", "rt"),
    ]
    [a] = eng.alerts()
    assert (a.start_ns, a.end_ns, a.peak, a.threshold) == (T0, T0 + 6 * S, 25.0, 15.0)
