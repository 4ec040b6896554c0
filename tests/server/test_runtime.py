"""Runtime: alerts reach Zenoh subscribers, with the server as the router or as its client."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch
from server.analytics.alerts import AlertKind, slip_kind
from server.runtime import SERVER_ALERTS_CHUNK, Runtime
from server.settings import Settings
from server.tooling.fleet_commands import vehicle_session
from server.tooling.router import router_config
from tests.support import free_port

pytestmark = pytest.mark.zenoh

S = 1_000_000_000
VEHICLES = [f"v{i:02d}" for i in range(30)]


def _slipping(seconds: int) -> np.ndarray:
    """MDSF rows of a vehicle whose left wheel slips 40 % for ``seconds`` (past any alert
    hold), its right wheel not at all."""
    left, right = MDSF_SPEC.slips
    r = MDSF_SPEC.empty_rows(seconds * 10)
    r["stamp_ns"] = time.time_ns() - seconds * S + np.arange(seconds * 10) * (S // 10)
    r[left.field] = 40.0
    r[right.field] = 0.0
    r["flags"] = MDSF_SPEC.flag_mask(left.valid_flag) | MDSF_SPEC.flag_mask(right.valid_flag)
    return r


@pytest.fixture(params=["embedded router", "client of a router"])
def runtime(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[Runtime, str]]:
    """A running server and the endpoint vehicles connect to."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = None
    zs: dict[str, object] = {"listen": [endpoint]}
    if request.param == "client of a router":
        router = zenoh.open(router_config([endpoint]))
        zs = {"connect": [endpoint]}
    settings = Settings.model_validate(
        {
            "zenoh": zs,
            "storage": {"data_dir": str(tmp_path / "data")},
            "viewer": {"enabled": False},
        }
    )
    rt = Runtime(settings)
    rt.open()
    try:
        yield rt, endpoint
    finally:
        rt.close()
        if router is not None:
            router.close()


def test_vehicle_and_server_alerts_are_published_under_their_keys(
    runtime: tuple[Runtime, str],
) -> None:
    rt, endpoint = runtime
    assert rt.alert_engine is not None
    with vehicle_session([endpoint]) as session:
        sub = session.declare_subscriber("fleet/*/alerts", zenoh.handlers.FifoChannel(1000))
        time.sleep(0.5)  # the subscription reaches the router
        for vid in VEHICLES:
            rt.alert_engine.on_estimates(EstimateBatch.of([(vid, _slipping(12))], MDSF_SPEC))
        rt.alert_engine.set_system_condition(AlertKind.STORAGE_DOWN, True)
        got: dict[str, list[dict[str, object]]] = {}
        deadline = time.monotonic() + 10
        while len(got) < len(VEHICLES) + 1 and time.monotonic() < deadline:
            sample = sub.handler.try_recv()
            if sample is None:
                time.sleep(0.01)
                continue
            owner = str(sample.key_expr).split("/")[1]
            got.setdefault(owner, []).append(json.loads(sample.payload.to_bytes()))
    assert sorted(got) == sorted([*VEHICLES, SERVER_ALERTS_CHUNK])
    for vid in VEHICLES:
        assert [e["event"] for e in got[vid]] == ["open"], got[vid]
        assert got[vid][0]["kind"] == slip_kind("mdsf", MDSF_SPEC.slips[0].key)
    assert got[SERVER_ALERTS_CHUNK][0]["kind"] == AlertKind.STORAGE_DOWN.value


def _alert_events(sub: zenoh.Subscriber, wait_s: float) -> list[dict[str, object]]:
    """Alert events received on ``sub`` within ``wait_s``."""
    got = []
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        sample = sub.handler.try_recv()
        if sample is None:
            time.sleep(0.01)
            continue
        got.append(json.loads(sample.payload.to_bytes()))
    return got


def test_a_joining_vehicle_is_not_stale_until_it_has_sent_a_row(
    runtime: tuple[Runtime, str],
) -> None:
    from estimator.config import WheeledRearDriveConfig

    rt, endpoint = runtime
    engine = rt.alert_engine
    assert engine is not None
    with vehicle_session([endpoint]) as session:
        sub = session.declare_subscriber("fleet/joiner/alerts", zenoh.handlers.FifoChannel(100))
        time.sleep(0.5)  # the subscription reaches the router
        rt.on_vehicle_config("joiner", WheeledRearDriveConfig())
        assert engine.check_stale(time.time_ns() + 60 * S) == []
        assert _alert_events(sub, 1.0) == []
        rows = _slipping(1)
        engine.on_estimates(EstimateBatch.of([("joiner", rows)], MDSF_SPEC))
        [stale] = engine.check_stale(time.time_ns() + 60 * S)
        events = [e for e in _alert_events(sub, 2.0) if e["kind"] == AlertKind.STALE.value]
    last_ns = int(rows["stamp_ns"][-1])
    assert stale.start_ns == last_ns
    assert [(e["event"], e["start_ns"]) for e in events] == [("open", last_ns)]


def test_estimator_failures_and_refused_configs_are_metrics_per_vehicle() -> None:
    from server.runtime import _ingest_families

    families = {
        f.name: f
        for f in _ingest_families({"v1": {"estimator_errors": 3, "configs_refused": 1}, "v2": {}})
    }
    for name, v1 in (("estimator_errors", 3.0), ("configs_refused", 1.0)):
        family = families[f"slipfleet_packets_{name}"]
        assert family.type == "counter"
        assert {s.labels["vehicle"]: s.value for s in family.samples} == {"v1": v1, "v2": 0.0}


def test_every_writer_counter_is_a_metric_with_its_own_value() -> None:
    import dataclasses

    from server.runtime import _WRITER_COUNTERS, _writer_families
    from server.storage.writer import WriterStats

    names = [name for name, _ in _WRITER_COUNTERS]
    values = {f.name: i + 1 for i, f in enumerate(dataclasses.fields(WriterStats))}
    stats = WriterStats(
        **{k: v for k, v in values.items() if k not in ("last_error", "healthy")},
        last_error=None,
        healthy=True,
    )
    got = {f.name: (f.type, [s.value for s in f.samples]) for f in _writer_families(stats)}
    want = {f"slipfleet_writer_{n}": ("counter", [float(values[n])]) for n in names}
    want["slipfleet_writer_backlog_rows"] = ("gauge", [float(values["backlog_rows"])])
    assert got == want


def test_a_config_naming_an_estimator_of_another_kind_is_refused_before_it_is_stored() -> None:
    from estimator.config import ConfigError, TrackedConfig
    from server.runtime import Runtime
    from server.settings import Settings

    runtime = Runtime(Settings())
    with pytest.raises(ConfigError, match="do not run on tracked vehicles"):
        runtime.check_vehicle_config("c", TrackedConfig(estimators=("mdsf",)))
    runtime.check_vehicle_config("c", TrackedConfig())  # its kind's defaults: none yet
