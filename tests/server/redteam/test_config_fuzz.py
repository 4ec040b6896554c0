"""Operator configs that break nothing: 2,000 generated configs (every field at its range's
ends, just outside, and at extreme floats; wrong types) over REST and over Zenoh to a real
``slipfleet serve`` while a baseline vehicle streams. The issue's two configs are refused with
422 and never stored; no answer is a 5xx; health stays 200 and the baseline vehicle's packets
go on being accepted."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estimator.config import WheeledRearDriveConfig, bound_of
from server.protocol import config_key
from tests.server.faults._harness import ServerProcess, wait_until
from tests.server.redteam._stack import client_session
from tests.support import VEHICLE_CLIENT

EXAMPLES = 2000
EXTREMES = (0.0, -0.0, 5e-324, -1.0, 1e12, 1e200, -1e200, 1.7976931348623157e308)


def _value(bound: Any) -> st.SearchStrategy[Any]:
    lo, hi = bound.low, bound.high
    edges = [lo, hi, (lo + hi) / 2, lo - abs(lo) * 1e-9 - 1e-12, hi + abs(hi) * 1e-9 + 1e-12]
    number = st.sampled_from([*edges, *EXTREMES]) | st.floats(allow_nan=False, allow_infinity=False)
    if bound.items is not None:
        return st.lists(number, min_size=bound.items[0], max_size=bound.items[1])
    if bound.integer:
        return st.sampled_from([int(lo), int(hi), int(hi) + 1, 2**63]) | number
    return number | st.sampled_from(["1", None, [1.0]])


def _section(cls: type[Any]) -> st.SearchStrategy[dict[str, Any]]:
    fields = {f.name: _value(b) for f in dataclasses.fields(cls) if (b := bound_of(f))}
    return st.fixed_dictionaries({}, optional=fields)


CONFIGS = st.fixed_dictionaries(
    {},
    optional={
        name: _section(type(getattr(WheeledRearDriveConfig(), name)))
        for name in ("geometry", "encoder", "noise", "slip")
    },
)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    tmp = tmp_path_factory.mktemp("fuzz")
    server = ServerProcess(tmp)
    server.start()
    vehicle: subprocess.Popen[bytes] | None = None
    try:
        server.wait_ready()
        vehicle = subprocess.Popen(
            [
                sys.executable,
                str(VEHICLE_CLIENT),
                "--connect",
                server.zenoh_listen,
                "--vehicle-id",
                "baseline",
                "--seconds",
                "600",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        with server.client() as c:
            wait_until(lambda: _accepted(c) > 0, 60, "the baseline vehicle's packets")
        yield server
    finally:
        if vehicle is not None:
            vehicle.kill()
            vehicle.wait(10)
        server.stop()


def _accepted(client: httpx.Client) -> int:
    text = client.get("/api/v1/metrics").text
    m = re.search(r'^slipfleet_packets_accepted_total\{vehicle="baseline"\} (\S+)$', text, re.M)
    return int(float(m.group(1))) if m else 0


@pytest.mark.zenoh
def test_the_issues_configs_are_refused_and_not_stored(served: ServerProcess) -> None:
    with served.client() as c:
        for body in ({"noise": {"accel_std_mps2": 1e200}}, {"slip": {"alert_hold_s": 1e12}}):
            r = c.put("/api/v1/vehicles/repro-1", json=body)
            assert r.status_code == 422, r.text
            assert c.get("/api/v1/vehicles/repro-1").status_code == 404
        assert c.get("/api/v1/health").status_code == 200


@pytest.mark.zenoh
@pytest.mark.slow
def test_config_fuzz_over_rest_and_zenoh_breaks_nothing(served: ServerProcess) -> None:
    statuses: Counter[int] = Counter()
    with served.client() as c, client_session(served.zenoh_listen) as session:
        before = _accepted(c)

        @settings(
            max_examples=EXAMPLES,
            deadline=None,
            derandomize=True,
            suppress_health_check=list(HealthCheck),
        )
        @given(CONFIGS, st.integers(0, 4))
        def put(body: dict[str, Any], slot: int) -> None:
            r = c.put(f"/api/v1/vehicles/fuzz-{slot}", json=body)
            statuses[r.status_code] += 1
            assert r.status_code in (200, 201, 422), (body, r.status_code, r.text)
            payload = json.dumps(body, allow_nan=True).encode()
            session.put(
                config_key("fleet", f"zfuzz-{slot}"),
                payload,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

        put()
        time.sleep(2.0)
        assert c.get("/api/v1/health").status_code == 200
        wait_until(lambda: _accepted(c) > before + 10, 30, "the baseline vehicle still accepted")
    print(f"{sum(statuses.values())} configs over REST: {dict(statuses)}")
    assert sum(statuses.values()) >= EXAMPLES
    assert statuses[422] > 0 and statuses[200] + statuses[201] > 0
