"""Access tokens on the REST API and the live WebSockets, with ``api.require_auth`` on.

Real parts only: a real SQLite store (the test runtime), real tokens issued into it, the app over
httpx's ASGI transport; the WebSocket tests run the app under a real uvicorn on 127.0.0.1.
"""

from __future__ import annotations

import hashlib
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from server.api import create_app
from server.api.deps import TOKEN_TOUCH_INTERVAL_NS, WS_BEARER_PROTOCOL
from server.app_main import ServerThread
from server.live.hub import LiveHub
from server.settings import Settings
from server.storage.base import Store
from server.tokens import Role, hash_token, is_well_formed, issue_token

from .conftest import ApiClient, FakeRuntime, make_settings, running

V = "/api/v1/vehicles"
Q = "start=2024-05-01T12:00:00Z&end=2024-05-01T13:00:00Z"


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return make_settings(tmp_path, require_auth=True)


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture
def tokens(client: ApiClient, store: Store) -> dict[Role, str]:
    """One token per role (issued straight into the store, as the CLI does)."""
    return {role: issue_token(store, f"t-{role}", role, time.time_ns())[0] for role in Role}


# ----------------------------------------------------------------------------- 401 / 403 / 2xx


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("GET", V),
        ("GET", f"{V}/t1"),
        ("PUT", f"{V}/t1"),
        ("DELETE", f"{V}/t1"),
        ("GET", f"{V}/t1/latest"),
        ("GET", f"{V}/t1/series?{Q}"),
        ("GET", f"{V}/t1/report?{Q}"),
        ("GET", f"/api/v1/fleet/report?{Q}"),
        ("GET", "/api/v1/alerts"),
        ("GET", "/api/v1/metrics"),
        ("GET", "/api/v1/tokens"),
        ("POST", "/api/v1/tokens"),
        ("DELETE", "/api/v1/tokens/1"),
    ],
)
def test_no_token_or_a_bad_one_is_401(
    client: ApiClient, tokens: dict[Role, str], method: str, path: str
) -> None:
    body = {"json": {}} if method in ("PUT", "POST") else {}
    r = client.request(method, path, **body)
    assert r.status_code == 401
    assert r.json()["error"] == "unauthorized"
    assert r.headers["www-authenticate"].startswith("Bearer")
    good = tokens[Role.ADMIN]
    for header in (
        f"Bearer {good[:-1]}x" if good[-1] != "x" else f"Bearer {good[:-1]}y",  # unknown
        "Bearer sft_short",  # malformed
        f"Basic {good}",  # not a bearer token
        "Bearer ",
    ):
        r = client.request(method, path, headers={"Authorization": header}, **body)
        assert r.status_code == 401, header


def test_health_stays_open(client: ApiClient) -> None:
    assert client.get("/api/v1/health").status_code == 200


def test_roles_viewer_operator_admin(client: ApiClient, tokens: dict[Role, str]) -> None:
    viewer, operator, admin = (_bearer(tokens[r]) for r in Role)
    # viewer: reads only
    assert client.get(V, headers=viewer).status_code == 200
    assert client.get("/api/v1/metrics", headers=viewer).status_code == 200
    assert client.get("/api/v1/alerts", headers=viewer).status_code == 200
    r = client.put(f"{V}/t1", json={}, headers=viewer)
    assert r.status_code == 403
    assert r.json()["error"] == "forbidden" and "operator" in r.json()["reason"]
    # operator: configures vehicles, deletes nothing, sees no tokens
    assert client.put(f"{V}/t1", json={}, headers=operator).status_code == 201
    assert client.get(f"{V}/t1", headers=viewer).status_code == 200
    assert client.delete(f"{V}/t1", headers=operator).status_code == 403
    assert client.delete(f"{V}/t1", headers=viewer).status_code == 403
    assert client.get("/api/v1/tokens", headers=operator).status_code == 403
    # admin: everything
    assert client.put(f"{V}/t1", json={}, headers=admin).status_code == 200
    assert client.delete(f"{V}/t1", headers=admin).status_code == 204
    assert client.get(f"{V}/t1", headers=admin).status_code == 404


def test_operator_cannot_mint_tokens(client: ApiClient, tokens: dict[Role, str]) -> None:
    r = client.post(
        "/api/v1/tokens",
        json={"name": "escalate", "role": "admin"},
        headers=_bearer(tokens[Role.OPERATOR]),
    )
    assert r.status_code == 403
    r = client.get("/api/v1/tokens", headers=_bearer(tokens[Role.ADMIN]))
    assert "escalate" not in [t["name"] for t in r.json()["data"]]


def test_revoked_token_is_401_at_once(
    client: ApiClient, store: Store, tokens: dict[Role, str]
) -> None:
    viewer = tokens[Role.VIEWER]
    assert client.get(V, headers=_bearer(viewer)).status_code == 200
    record = store.get_token(hash_token(viewer))
    assert record is not None
    r = client.delete(f"/api/v1/tokens/{record.id}", headers=_bearer(tokens[Role.ADMIN]))
    assert r.status_code == 204
    r = client.get(V, headers=_bearer(viewer))
    assert r.status_code == 401
    assert "revoked" in r.json()["reason"]
    assert client.get(V, headers=_bearer(tokens[Role.OPERATOR])).status_code == 200
    r = client.delete("/api/v1/tokens/999999", headers=_bearer(tokens[Role.ADMIN]))
    assert r.status_code == 404


# ----------------------------------------------------------------------------- token routes


def test_expired_token_is_401(client: ApiClient, tokens: dict[Role, str]) -> None:
    admin = _bearer(tokens[Role.ADMIN])
    before_ns = time.time_ns()
    body = {"name": "brief", "role": "viewer", "expires_in_s": 1}
    created = client.post("/api/v1/tokens", json=body, headers=admin).json()
    assert 0 < created["expires_ns"] - before_ns - 10**9 < 5 * 10**9
    assert client.get(V, headers=_bearer(created["token"])).status_code == 200
    time.sleep(max(0.0, (created["expires_ns"] - time.time_ns()) / 1e9) + 0.01)
    r = client.get(V, headers=_bearer(created["token"]))
    assert r.status_code == 401
    assert "expired" in r.json()["reason"]
    listed = client.get("/api/v1/tokens", headers=admin).json()["data"]
    assert (
        next(t for t in listed if t["id"] == created["id"])["expires_ns"] == created["expires_ns"]
    )
    assert all(t["expires_ns"] is None for t in listed if t["id"] != created["id"])


def test_token_routes_create_list_revoke(client: ApiClient, tokens: dict[Role, str]) -> None:
    admin = _bearer(tokens[Role.ADMIN])
    r = client.post("/api/v1/tokens", json={"name": "grafana", "role": "viewer"}, headers=admin)
    assert r.status_code == 201
    created = r.json()
    new = created["token"]
    assert is_well_formed(new)
    assert created["role"] == "viewer" and created["name"] == "grafana"
    assert created["revoked_ns"] is None and created["last_used_ns"] is None
    assert client.get(V, headers=_bearer(new)).status_code == 200

    listed = client.get("/api/v1/tokens", headers=admin).json()
    assert listed["count"] == 4
    mine = next(t for t in listed["data"] if t["id"] == created["id"])
    assert "token" not in mine  # never shown again
    assert mine["last_used_ns"] is not None  # the GET above used it
    assert new not in client.get("/api/v1/tokens", headers=admin).text

    assert client.delete(f"/api/v1/tokens/{created['id']}", headers=admin).status_code == 204
    assert client.get(V, headers=_bearer(new)).status_code == 401
    listed = client.get("/api/v1/tokens", headers=admin).json()
    assert next(t for t in listed["data"] if t["id"] == created["id"])["revoked_ns"] is not None


@pytest.mark.parametrize(
    "body",
    [
        {"name": "x", "role": "root"},
        {"name": "", "role": "viewer"},
        {"name": "a\nb", "role": "viewer"},
        {"name": "x" * 101, "role": "viewer"},
        {"role": "viewer"},
        {"name": "x", "role": "viewer", "expires_in_s": 0},
        {"name": "x", "role": "viewer", "expires_in_s": -5},
        {"name": "x", "role": "viewer", "expires_in_s": 1.5},
        {"name": "x", "role": "viewer", "expires_in_s": True},
        {"name": "x", "role": "viewer", "expires_in_s": 10 * 366 * 86_400 + 1},
    ],
)
def test_token_create_validates(
    client: ApiClient, tokens: dict[Role, str], body: dict[str, Any]
) -> None:
    r = client.post("/api/v1/tokens", json=body, headers=_bearer(tokens[Role.ADMIN]))
    assert r.status_code == 422


def test_tokens_are_stored_hashed(
    client: ApiClient, settings: Settings, tokens: dict[Role, str]
) -> None:
    r = client.post(
        "/api/v1/tokens",
        json={"name": "hashed", "role": "operator"},
        headers=_bearer(tokens[Role.ADMIN]),
    )
    token = r.json()["token"]
    path = settings.storage.data_dir / settings.storage.sqlite_file
    with sqlite3.connect(path) as conn:
        rows = conn.execute("SELECT * FROM api_tokens WHERE name = 'hashed'").fetchall()
        dump = "\n".join(conn.iterdump())
    assert len(rows) == 1
    assert hashlib.sha256(token.encode()).hexdigest() in rows[0]
    assert token not in dump  # nowhere in the database, in any form but the hash
    assert token.removeprefix("sft_") not in dump


def test_last_used_is_written_at_most_once_a_minute(
    client: ApiClient, store: Store, tokens: dict[Role, str]
) -> None:
    viewer = tokens[Role.VIEWER]
    assert client.get(V, headers=_bearer(viewer)).status_code == 200
    first = store.get_token(hash_token(viewer))
    assert first is not None and first.last_used_ns is not None
    assert client.get(V, headers=_bearer(viewer)).status_code == 200
    second = store.get_token(hash_token(viewer))
    assert second is not None and second.last_used_ns == first.last_used_ns
    assert TOKEN_TOUCH_INTERVAL_NS == 60 * 1_000_000_000


# ----------------------------------------------------------------------------- every route


def _expected_role(path: str, method: str) -> Role | None:
    if path == "/api/v1/health":
        return None
    if path.endswith("/calibration/{estimator}") and method == "DELETE":
        return Role.OPERATOR  # a calibration reset: an operator's, like the commands
    if path.startswith("/api/v1/tokens") or method == "DELETE":
        return Role.ADMIN
    if method in ("PUT", "POST", "PATCH"):
        return Role.OPERATOR
    return Role.VIEWER


def test_every_operation_asks_for_its_role(client: ApiClient, tokens: dict[Role, str]) -> None:
    """Walk the OpenAPI document: each operation refuses the role below its own with 403 and
    admits its own (GET viewer, PUT operator, DELETE and /tokens admin, /health open)."""
    spec = client.get("/openapi.json").json()
    checked = 0
    for template, ops in spec["paths"].items():
        path = template.replace("{vehicle_id}", "t1").replace("{token_id}", "999999")
        if "report" in path or "series" in path:
            path += f"?{Q}"
        for method in ops:
            verb = method.upper()
            body = {"json": {"name": "x", "role": "viewer"} if verb == "POST" else {}}
            kwargs: dict[str, Any] = body if verb in ("PUT", "POST") else {}
            want = _expected_role(template, verb)
            if want is None:
                assert client.request(verb, path, **kwargs).status_code not in (401, 403)
                continue
            if want.rank > 0:
                below = next(r for r in Role if r.rank == want.rank - 1)
                r = client.request(verb, path, headers=_bearer(tokens[below]), **kwargs)
                assert r.status_code == 403, (verb, path, below)
            r = client.request(verb, path, headers=_bearer(tokens[want]), **kwargs)
            assert r.status_code not in (401, 403), (verb, path, want, r.text)
            checked += 1
    assert checked >= 12


def test_auth_off_admits_everyone(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, require_auth=False)
    with running(create_app(settings, FakeRuntime(settings))) as client:
        assert client.put(f"{V}/t1", json={}).status_code == 201
        assert client.delete(f"{V}/t1").status_code == 204
        assert client.get("/api/v1/tokens").status_code == 200


# ----------------------------------------------------------------------------- WebSockets


@pytest.fixture
def served(settings: Settings) -> Iterator[tuple[ServerThread, FakeRuntime]]:
    runtime = FakeRuntime(settings)
    runtime.live_hub = LiveHub()
    app = create_app(settings, runtime)
    server = ServerThread(app, "127.0.0.1", 0)
    server.start()
    try:
        yield server, runtime
    finally:
        server.stop()


def _ws(server: ServerThread, path: str, **kwargs: Any) -> Any:
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{server.port}{path}", open_timeout=10, **kwargs)


def test_websocket_needs_a_token(served: tuple[ServerThread, FakeRuntime]) -> None:
    from websockets.exceptions import InvalidStatus

    server, runtime = served
    token, record = issue_token(runtime.store, "dash", Role.VIEWER, time.time_ns())
    for path, kwargs in (
        ("/api/v1/live/fleet", {}),
        ("/api/v1/live/fleet?token=sft_nope", {}),
        ("/api/v1/live/vehicles/a", {"subprotocols": [WS_BEARER_PROTOCOL, "sft_nope"]}),
    ):
        with pytest.raises(InvalidStatus) as exc:
            _ws(server, path, **kwargs)
        assert exc.value.response.status_code == 403, path

    # the subprotocol way (what a browser can send): the server accepts the marker, not the token
    with _ws(server, "/api/v1/live/fleet", subprotocols=[WS_BEARER_PROTOCOL, token]) as ws:
        assert ws.subprotocol == WS_BEARER_PROTOCOL
        assert '"type":"fleet"' in ws.recv(timeout=10)
    # the query parameter way
    with _ws(server, f"/api/v1/live/vehicles/a?token={token}") as ws:
        assert '"type":"waiting"' in ws.recv(timeout=10)
    # the header way (non-browser clients)
    with _ws(server, "/api/v1/live/fleet", additional_headers=_bearer(token)) as ws:
        assert '"type":"fleet"' in ws.recv(timeout=10)

    runtime.store.revoke_token(record.id, time.time_ns())
    with pytest.raises(InvalidStatus) as exc:
        _ws(server, "/api/v1/live/fleet", subprotocols=[WS_BEARER_PROTOCOL, token])
    assert exc.value.response.status_code == 403


def test_body_limit_holds_with_and_without_a_token(
    client: ApiClient, tokens: dict[Role, str]
) -> None:
    big = {"name": "x" * 100_000, "role": "viewer"}  # over ApiLimits.max_body_bytes (64 KiB)
    for headers in ({}, _bearer(tokens[Role.ADMIN])):
        r = client.post("/api/v1/tokens", json=big, headers=headers)
        assert r.status_code == 413
        assert r.json()["error"] == "payload_too_large"


def test_websocket_is_closed_when_its_token_expires(
    served: tuple[ServerThread, FakeRuntime],
) -> None:
    from websockets.exceptions import ConnectionClosed

    from server.api.routes.live import REVOCATION_POLL_S

    server, runtime = served
    lifetime_ns = 1_500_000_000
    brief, record = issue_token(runtime.store, "brief", Role.VIEWER, time.time_ns(), lifetime_ns)
    lasting, _ = issue_token(runtime.store, "lasting", Role.VIEWER, time.time_ns())
    assert record.expires_ns is not None
    with (
        _ws(
            server, "/api/v1/live/fleet?interval_ms=250", subprotocols=[WS_BEARER_PROTOCOL, brief]
        ) as ws,
        _ws(
            server, "/api/v1/live/fleet?interval_ms=250", subprotocols=[WS_BEARER_PROTOCOL, lasting]
        ) as other,
    ):
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                ws.recv(timeout=10)
        late_s = (time.time_ns() - record.expires_ns) / 1e9
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
        assert -0.05 < late_s < REVOCATION_POLL_S + 0.5
        assert '"type":"fleet"' in other.recv(timeout=5)  # the lasting token streams on
