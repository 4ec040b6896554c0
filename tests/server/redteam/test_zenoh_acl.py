"""A credentialed vehicle attacking over real Zenoh on loopback (the server's embedded router
with credentials and its ACL, SQLite in ``tmp_path``).

* Wildcard subscriptions: vehicle ``v1`` subscribes to ``fleet/**``, ``**``, another vehicle's
  keys and every alerts key, while ``v2`` streams and the server publishes alerts for ``v1``,
  ``v2`` and the whole server. ``v1`` must get nothing but its own alerts; ``v2``'s own alerts
  subscription (the control) gets ``v2``'s.
* Fake alerts: ``v1`` puts alert-shaped JSON on ``v2``'s and the server's alerts keys and on its
  own. Nothing reaches ``v2`` or the server's session, and the server's alert list stays empty.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from server.analytics.alerts import AlertKind
from server.protocol import Stream, sensor_key
from server.runtime import SERVER_ALERTS_CHUNK, Runtime
from server.settings import Settings
from tests.server.ingest.test_zenoh_auth import (  # the secured server of the ACL tests
    PW,
    _publish,
    _vehicle,
    _wait_for,
    secured_runtime,
)

__all__ = ["secured_runtime"]  # a fixture, used by name


class _Inbox:
    """Every sample a set of subscriptions receives: ``(subscribed key, sample key, payload)``."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, str, bytes]] = []
        self._lock = threading.Lock()

    def listen(self, session: zenoh.Session, key_expr: str) -> zenoh.Subscriber[None]:
        def on_sample(sample: zenoh.Sample) -> None:
            with self._lock:
                self.samples.append((key_expr, str(sample.key_expr), sample.payload.to_bytes()))

        return session.declare_subscriber(key_expr, on_sample)

    def sample_keys(self) -> set[str]:
        with self._lock:
            return {key for _, key, _ in self.samples}


@pytest.fixture
def stack(
    secured_runtime: tuple[Runtime, Settings, str],
) -> Iterator[tuple[Runtime, str, zenoh.Session, zenoh.Session]]:
    runtime, settings, endpoint = secured_runtime
    with _vehicle(endpoint, "v1", PW["v1"]) as v1, _vehicle(endpoint, "v2", PW["v2"]) as v2:
        yield runtime, settings.zenoh.key_prefix, v1, v2


def _server_alerts(runtime: Runtime) -> None:
    """A real server-wide alert opened and closed again (the health loop closes it)."""
    assert runtime.alert_engine is not None
    runtime.alert_engine.set_system_condition(AlertKind.STORAGE_DOWN, True)


@pytest.mark.zenoh
def test_wildcard_subscriptions_get_nothing_of_others(
    stack: tuple[Runtime, str, zenoh.Session, zenoh.Session],
) -> None:
    runtime, prefix, v1, v2 = stack
    attacker, control = _Inbox(), _Inbox()
    wildcards = [
        "**",
        f"{prefix}/**",
        f"{prefix}/*/alerts",
        f"{prefix}/v2/**",
        f"{prefix}/v2/alerts",
        f"{prefix}/v2/sensors/*",
        f"{prefix}/{SERVER_ALERTS_CHUNK}/**",
    ]
    subs = [attacker.listen(v1, k) for k in wildcards]
    subs.append(control.listen(v2, f"{prefix}/v2/alerts"))
    time.sleep(0.5)  # the declarations reach the router

    _publish(v2, sensor_key(prefix, "v2", Stream.GNSS), 20)
    assert runtime.pipeline is not None
    pipeline = runtime.pipeline
    _wait_for(lambda: pipeline.counters_snapshot().get("v2", {}).get("received") == 20, "v2 in")
    for vid in ("v1", "v2"):
        runtime._publish_alert(vid, {"event": "open", "marker": f"alert-for-{vid}"})
    _server_alerts(runtime)
    _wait_for(lambda: f"{prefix}/v2/alerts" in control.sample_keys(), "v2's own alert")
    time.sleep(2.0)  # the health loop closes the server-wide alert: more traffic to leak

    leaked = attacker.sample_keys() - {f"{prefix}/v1/alerts"}  # its own alerts are v1's to see
    assert leaked == set(), f"v1's wildcard subscriptions received {sorted(leaked)}"
    assert not any(b"alert-for-v2" in payload for _, _, payload in attacker.samples)
    for sub in subs:
        sub.undeclare()


@pytest.mark.zenoh
def test_fake_alerts_from_a_vehicle_are_dropped_or_ignored(
    stack: tuple[Runtime, str, zenoh.Session, zenoh.Session],
) -> None:
    runtime, prefix, v1, v2 = stack
    victim, server_side = _Inbox(), _Inbox()
    assert runtime.session is not None  # the router's own session: the ACL does not filter it
    subs = [
        victim.listen(v2, f"{prefix}/v2/alerts"),
        server_side.listen(runtime.session, f"{prefix}/v2/alerts"),
        server_side.listen(runtime.session, f"{prefix}/{SERVER_ALERTS_CHUNK}/alerts"),
    ]
    time.sleep(0.5)
    fake = {
        "event": "open",
        "alert": {"id": 1, "vehicle_id": "v2", "kind": "high_slip", "start_ns": time.time_ns()},
    }
    for owner in ("v2", SERVER_ALERTS_CHUNK, "v1"):
        for _ in range(20):
            v1.put(f"{prefix}/{owner}/alerts", json.dumps({**fake, "vehicle_id": owner}))
    # then v1's own sensor packets on the same link: once they are in, the fakes sent before
    # them would have arrived too had the router let them through
    _publish(v1, sensor_key(prefix, "v1", Stream.GNSS), 10)
    assert runtime.pipeline is not None
    pipeline = runtime.pipeline
    _wait_for(lambda: pipeline.counters_snapshot().get("v1", {}).get("received") == 10, "v1 in")
    time.sleep(0.5)

    assert victim.samples == []
    assert server_side.samples == []
    assert runtime.alert_engine is not None
    assert runtime.alert_engine.alerts() == [], "the server took a vehicle's put as an alert"
    assert "v2" not in pipeline.counters_snapshot()
    for sub in subs:
        sub.undeclare()


@pytest.mark.zenoh
def test_a_vehicle_cannot_forge_its_own_alerts_or_status(
    stack: tuple[Runtime, str, zenoh.Session, zenoh.Session],
) -> None:
    """``v1`` puts alert- and status-shaped JSON on its *own* alerts and status keys (and on
    keys of its own space that are no sensor stream). A second ``v1`` session (the vehicle's
    own display) and the server's session listen there: neither gets a forged sample."""
    runtime, prefix, v1, _ = stack
    assert runtime.session is not None
    owner, server_side = _Inbox(), _Inbox()
    told = [f"{prefix}/v1/alerts", f"{prefix}/v1/status"]
    elsewhere = [f"{prefix}/v1/alerts/extra", f"{prefix}/v1/sensors/gnss/extra", f"{prefix}/v1/x"]
    endpoint = runtime.settings.zenoh.listen[0]
    with _vehicle(endpoint, "v1", PW["v1"]) as display:
        subs = [owner.listen(display, k) for k in told]
        subs += [server_side.listen(runtime.session, k) for k in [*told, *elsewhere]]
        time.sleep(0.5)
        forged = {"event": "open", "marker": "forged-by-v1", "vehicle_id": "v1"}
        for key in [*told, *elsewhere]:
            for _ in range(20):
                v1.put(key, json.dumps(forged))
            v1.delete(key)
        _publish(v1, sensor_key(prefix, "v1", Stream.GNSS), 10)  # the barrier: same link, after
        assert runtime.pipeline is not None
        pipeline = runtime.pipeline
        _wait_for(lambda: pipeline.counters_snapshot().get("v1", {}).get("received") == 10, "v1")
        runtime._publish_alert("v1", {"event": "open", "marker": "from-the-server"})  # control
        _wait_for(lambda: f"{prefix}/v1/alerts" in owner.sample_keys(), "the server's alert")
        time.sleep(0.5)
        for sub in subs:
            sub.undeclare()

    heard = [(key, payload) for _, key, payload in owner.samples + server_side.samples]
    forged_heard = [key for key, payload in heard if b"forged-by-v1" in payload or not payload]
    assert forged_heard == [], f"forged samples got through on {sorted(set(forged_heard))}"
    assert any(b"from-the-server" in payload for _, _, payload in owner.samples)
