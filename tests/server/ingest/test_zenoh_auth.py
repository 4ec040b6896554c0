"""Vehicle authentication and ACL on the embedded router.

The config tests need no network. The ``zenoh`` tests run the real server runtime (embedded
router on a free 127.0.0.1 port, multicast scouting off, SQLite in ``tmp_path``) and real
vehicle client sessions built by :func:`server.ingest.make_config`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

import msgpack
import pytest
import zenoh

from estimator.types import GnssSample
from server.ingest import make_config
from server.ingest.zenoh_session import (
    CredentialsError,
    acl_config,
    read_credential_users,
    router_config_dict,
)
from server.protocol import Stream, encode_gnss, sensor_key
from server.runtime import Runtime
from server.settings import Settings, ZenohSettings
from tests.support import free_port

PW = {"v1": "v1-password-0123456789", "v2": "v2-password-0123456789"}


def _write_credentials(path: Path, pairs: dict[str, str]) -> Path:
    path.write_text("".join(f"{u}:{p}\n" for u, p in pairs.items()))
    path.chmod(0o600)
    return path


# ----------------------------------------------------------------------------- config only


def test_credentials_file_is_checked(tmp_path: Path) -> None:
    good = _write_credentials(tmp_path / "ok", {"tractor-1": "x" * 20, "srv@ops": "y" * 20})
    assert read_credential_users(good, server_user="srv@ops") == ["tractor-1", "srv@ops"]
    with pytest.raises(CredentialsError, match="neither a vehicle id"):
        read_credential_users(good)  # not a vehicle id, and not named as the server
    for text, why in (
        ("tractor-1\n", "expected user:password"),
        ("tractor-1:\n", "expected user:password"),
        ("a:pw-one-0123456789\na:pw-two-0123456789\n", "twice"),
        ("fleet/*:pw-0123456789abcdef\n", "neither a vehicle id"),
        ("# comment\n", "expected user:password"),
    ):
        bad = tmp_path / "bad"
        bad.write_text(text)
        with pytest.raises(CredentialsError, match=why) as exc:
            read_credential_users(bad)
        assert "pw-" not in str(exc.value)  # never a password in the message
    with pytest.raises(CredentialsError):
        read_credential_users(tmp_path / "missing")


def test_acl_allows_each_vehicle_its_own_key_space_only() -> None:
    acl = acl_config("fleet", ["v1", "v2"], "srv")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["v1/publish"] == {
        "id": "v1/publish",
        "permission": "allow",
        "flows": ["ingress"],
        "messages": ["put"],
        "key_exprs": ["fleet/v1/sensors/*", "fleet/v1/config"],
    }
    # a vehicle may hear its own alerts and status (refusal counts), nobody else's
    assert rules["v2/alerts-receive"]["key_exprs"] == ["fleet/v2/alerts", "fleet/v2/status"]
    assert rules["v2/alerts-subscribe"]["key_exprs"] == ["fleet/v2/alerts", "fleet/v2/status"]
    # the one deny: no vehicle puts or deletes on an alerts or status key, its own included
    denied = [r for r in acl["rules"] if r["permission"] == "deny"]
    assert denied == [rules["vehicles/never-forge-server-keys"]]
    assert denied[0]["flows"] == ["ingress"] and denied[0]["messages"] == ["put", "delete"]
    assert denied[0]["key_exprs"] == ["fleet/*/alerts/**", "fleet/*/status/**"]
    subjects = {s["id"]: s["usernames"] for s in acl["subjects"]}
    assert subjects == {"vehicle/v1": ["v1"], "vehicle/v2": ["v2"], "server": ["srv"]}
    policy_of = {p["subjects"][0]: p["rules"] for p in acl["policies"]}
    assert policy_of["vehicle/v1"] == [
        "v1/publish",
        "v1/alerts-subscribe",
        "v1/alerts-receive",
        "vehicles/see-server-subscriptions",
        "vehicles/never-forge-server-keys",
    ]
    assert rules["vehicles/see-server-subscriptions"]["flows"] == ["egress"]
    assert rules["vehicles/see-server-subscriptions"]["messages"] == ["declare_subscriber"]
    assert policy_of["server"] == ["server/ingress", "server/egress"]


def test_router_refuses_to_listen_openly_without_credentials(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="credentials_file"):
        make_config(ZenohSettings.model_validate({"listen": ["tcp/0.0.0.0:7447"]}))
    with pytest.raises(ValueError, match="credentials_file"):
        make_config(ZenohSettings.model_validate({"listen": ["tcp/[::]:7447"]}))
    for endpoint in ("tcp/127.0.0.1:7447", "tcp/localhost:7447", "tcp/[::1]:7447"):
        make_config(ZenohSettings.model_validate({"listen": [endpoint]}))
    open_ok = ZenohSettings.model_validate(
        {"listen": ["tcp/0.0.0.0:7447"], "allow_anonymous": True}
    )
    assert make_config(open_ok).get_json("mode") == '"router"'
    creds = _write_credentials(tmp_path / "c", PW)
    secured = ZenohSettings.model_validate(
        {"listen": ["tcp/0.0.0.0:7447"], "credentials_file": str(creds)}
    )
    config = make_config(secured)
    assert json.loads(config.get_json("transport/auth/usrpwd/dictionary_file")) == str(
        creds.resolve()
    )
    assert json.loads(config.get_json("access_control/default_permission")) == "deny"
    no_acl = secured.model_copy(update={"acl": False})
    assert json.loads(make_config(no_acl).get_json("access_control/enabled")) is False


def test_standalone_router_config_matches_the_deploy_example(tmp_path: Path) -> None:
    """``deploy/zenoh-router.json5`` is what ``slipfleet zenoh-router-config`` writes for its
    example credentials (two tractors and the server)."""
    repo = Path(__file__).resolve().parents[3]
    example = zenoh.Config.from_file(str(repo / "deploy" / "zenoh-router.json5"))
    creds = _write_credentials(
        tmp_path / "vehicles.credentials",
        {"tractor-001": "a" * 24, "tractor-002": "b" * 24, "slipfleet-server": "c" * 24},
    )
    generated = router_config_dict(
        ZenohSettings.model_validate(
            {"credentials_file": str(creds), "username": "slipfleet-server", "password": "c" * 24}
        ),
        listen=["tcp/0.0.0.0:7447"],
    )
    loaded = zenoh.Config.from_json5(json.dumps(generated))  # normalised as Zenoh reads it
    for key in (
        "access_control",
        "mode",
        "listen/endpoints",
        "scouting",
        "transport/unicast/max_sessions",
        "transport/shared_memory/enabled",
    ):
        assert json.loads(example.get_json(key)) == json.loads(loaded.get_json(key)), key
    assert json.loads(example.get_json("access_control/default_permission")) == "deny"
    assert json.loads(example.get_json("transport/auth/usrpwd/dictionary_file")).endswith(
        "zenoh.credentials"
    )


# ----------------------------------------------------------------------------- real Zenoh


def _wait_for(cond: Callable[[], object], what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not in time")
        time.sleep(0.02)


def _vehicle(endpoint: str, user: str | None, password: str | None) -> zenoh.Session:
    return zenoh.open(
        make_config(
            ZenohSettings.model_validate(
                {"connect": [endpoint], "username": user, "password": password}
            )
        )
    )


@pytest.fixture
def secured_runtime(tmp_path: Path) -> Iterator[tuple[Runtime, Settings, str]]:
    yield from _secured_runtime(tmp_path)


@pytest.fixture(params=[0, 2], ids=["pipeline", "workers"])
def secured_runtimes(
    tmp_path: Path, request: pytest.FixtureRequest
) -> Iterator[tuple[Runtime, Settings, str]]:
    """The secured runtime with one pipeline thread, and with worker processes."""
    yield from _secured_runtime(tmp_path, workers=request.param)


def _secured_runtime(tmp_path: Path, workers: int = 0) -> Iterator[tuple[Runtime, Settings, str]]:
    creds = _write_credentials(tmp_path / "vehicles.credentials", PW)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings.model_validate(
        {
            "ingest": {"workers": workers},
            "zenoh": {"listen": [endpoint], "credentials_file": str(creds)},
            "storage": {"data_dir": str(tmp_path / "data"), "commit_interval_s": 0.1},
            "api": {"require_auth": True},
            "viewer": {"enabled": False},
        }
    )
    runtime = Runtime(settings)
    runtime.open()
    try:
        yield runtime, settings, endpoint
    finally:
        runtime.close()


@pytest.mark.zenoh
def test_wrong_credentials_cannot_connect(
    secured_runtime: tuple[Runtime, Settings, str],
) -> None:
    _, _, endpoint = secured_runtime
    for user, password in (
        ("v1", "not-the-password"),
        ("v1", PW["v2"]),  # another vehicle's password
        ("nobody", PW["v1"]),
        (None, None),  # no credentials at all
    ):
        with pytest.raises(zenoh.ZError):
            _vehicle(endpoint, user, password)
    with _vehicle(endpoint, "v1", PW["v1"]) as session:
        assert session.info.routers_zid()


def _gnss(k: int, t0_ns: int) -> bytes:
    g = GnssSample(t0_ns + k * 100_000_000, (0.0, 2.0, 0.0), 0.0, 0.0, 0.0, 48.0, 11.0, 500.0)
    return encode_gnss(g, k)


def _publish(session: zenoh.Session, key: str, n: int) -> None:
    pub = session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    # a client sends only once it knows of a matching subscriber (the ACL lets the router say)
    _wait_for(lambda: getattr(pub.matching_status, "matching", False), f"matching on {key}")
    t0_ns = time.time_ns()
    for k in range(n):
        pub.put(_gnss(k, t0_ns))
    pub.undeclare()


@pytest.mark.zenoh
def test_a_vehicle_cannot_publish_as_another(
    secured_runtime: tuple[Runtime, Settings, str],
) -> None:
    runtime, settings, endpoint = secured_runtime
    prefix = settings.zenoh.key_prefix
    assert runtime.pipeline is not None
    pipeline = runtime.pipeline

    def received(vid: str) -> int:
        return pipeline.counters_snapshot().get(vid, {}).get("received", 0)

    with _vehicle(endpoint, "v1", PW["v1"]) as v1:
        # spoofed packets first, then v1's own on the same link: once v1's own arrived, the
        # spoofed ones would have arrived before them had the router let them through
        _publish(v1, sensor_key(prefix, "v2", Stream.GNSS), 20)
        v1.put(f"{prefix}/v2/config", b"{}")
        _publish(v1, sensor_key(prefix, "v1", Stream.GNSS), 20)
        _wait_for(lambda: received("v1") == 20, "v1's own packets")
        time.sleep(0.5)
        assert received("v2") == 0
        assert "v2" not in pipeline.counters_snapshot()

    # v2's key space itself works: v2 with its own credentials gets through
    with _vehicle(endpoint, "v2", PW["v2"]) as v2:
        _publish(v2, sensor_key(prefix, "v2", Stream.GNSS), 5)
        _wait_for(lambda: received("v2") == 5, "v2's own packets")
    # what is stored: v2's own five packets, none of the twenty v1 sent under v2's key
    store = runtime.store
    _wait_for(lambda: {r.vehicle_id for r in store.list_vehicles()} == {"v1", "v2"}, "vehicles")
    _wait_for(lambda: store.get_counters("v2").get("received") == 5, "stored counters")
    assert store.get_counters("v1")["received"] == 20
    time.sleep(1.5)  # another counter flush
    assert store.get_counters("v2")["received"] == 5


def _refused_gnss(k: int, t0_ns: int) -> bytes:
    """A GNSS packet refused ``wrong_type``: a velocity of two numbers."""
    m = msgpack.unpackb(_gnss(k, t0_ns))
    m["vel_enu_mps"] = [1.0, 2.0]
    return bytes(msgpack.packb(m, use_bin_type=True))


def _json_into(messages: list[dict[str, object]]) -> Callable[[zenoh.Sample], None]:
    def on_sample(sample: zenoh.Sample) -> None:
        messages.append(json.loads(sample.payload.to_bytes()))

    return on_sample


def _matching(pub: zenoh.Publisher) -> bool:
    return bool(getattr(pub.matching_status, "matching", False))


@pytest.mark.zenoh
def test_a_refused_vehicle_hears_its_status_and_the_server_logs_it(
    secured_runtimes: tuple[Runtime, Settings, str], caplog: pytest.LogCaptureFixture
) -> None:
    """v1 subscribes to its own status (the ACL lets it) and to v2's (the ACL drops that);
    both send refused packets; v1 hears its own counts by reason, and the server logs each
    vehicle's first refusal once."""
    _, settings, endpoint = secured_runtimes
    prefix = settings.zenoh.key_prefix
    caplog.set_level(logging.WARNING, logger="server.ingest.status")
    heard: dict[str, list[dict[str, object]]] = {"v1": [], "v2": []}
    with _vehicle(endpoint, "v1", PW["v1"]) as v1, _vehicle(endpoint, "v2", PW["v2"]) as v2:
        for vid, messages in heard.items():
            v1.declare_subscriber(f"{prefix}/{vid}/status", _json_into(messages))
        for session, vid, n in ((v1, "v1", 7), (v2, "v2", 3)):
            pub = session.declare_publisher(
                sensor_key(prefix, vid, Stream.GNSS),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
            )
            _wait_for(partial(_matching, pub), "matching")
            t0_ns = time.time_ns()
            for k in range(n):
                pub.put(_refused_gnss(k, t0_ns))
        _wait_for(lambda: any(m["refused"] == {"wrong_type": 7} for m in heard["v1"]), "status")
        time.sleep(1.5)  # another status round: v2's would have come by now
    status = next(m for m in heard["v1"] if m["refused"] == {"wrong_type": 7})
    assert status["vehicle_id"] == "v1" and status["window_s"] == 60
    assert status["refused_total"] == 7
    assert heard["v2"] == []
    lines = [r.getMessage() for r in caplog.records]
    assert lines.count("vehicle v1: packets refused (wrong_type): 7") == 1
    assert lines.count("vehicle v2: packets refused (wrong_type): 3") == 1
