"""App factory: lifespan, routing, error mapping, CORS, OpenAPI."""

from __future__ import annotations

import importlib
from pathlib import Path

from fastapi import APIRouter

import server.api.app as app_module
from server.api import API_ROUTERS, create_app
from server.settings import Settings

from .conftest import ApiClient, FakeRuntime, make_settings, running


def test_nothing_built_at_import() -> None:
    module = importlib.reload(app_module)
    assert not any(type(v).__name__ == "FastAPI" for v in vars(module).values())


def test_lifespan_opens_and_closes_the_runtime(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    runtime = FakeRuntime(settings)
    app = create_app(settings, runtime)
    assert runtime.opened == 0
    with running(app) as client:
        assert runtime.opened == 1
        assert client.get("/api/v1/health").status_code == 200
    assert runtime.closed == 1
    assert app.state.runtime is None


def test_unknown_path_and_method_are_json(client: ApiClient) -> None:
    r = client.get("/api/v1/nothing")
    assert r.status_code == 404
    assert r.json() == {"error": "not_found", "reason": "Not Found"}
    r = client.request("POST", "/api/v1/vehicles")
    assert r.status_code == 405
    assert r.json()["error"] == "method_not_allowed"


def test_cors_closed_by_default(client: ApiClient) -> None:
    r = client.get("/api/v1/vehicles", headers={"Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in r.headers
    r = client.options(
        "/api/v1/vehicles",
        headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "GET"},
    )
    assert "access-control-allow-origin" not in r.headers


def test_cors_open_for_listed_origins(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, cors_origins=["http://dash.example"])
    with running(create_app(settings, FakeRuntime(settings))) as client:
        r = client.get("/api/v1/vehicles", headers={"Origin": "http://dash.example"})
        assert r.headers["access-control-allow-origin"] == "http://dash.example"
        r = client.get("/api/v1/vehicles", headers={"Origin": "http://evil.example"})
        assert "access-control-allow-origin" not in r.headers
        r = client.put(
            "/api/v1/vehicles/t1",
            json={"estimators": ["x" * 100_000]},
            headers={"Origin": "http://dash.example"},
        )
        assert r.status_code == 413
        assert r.headers["access-control-allow-origin"] == "http://dash.example"


def test_default_bind_is_loopback() -> None:
    assert Settings().api.host == "127.0.0.1"


def test_openapi_is_generator_ready(client: ApiClient) -> None:
    spec = client.get("/openapi.json").json()
    ops = [op for path in spec["paths"].values() for op in path.values()]
    ids = [op["operationId"] for op in ops]
    assert len(ids) == len(set(ids))
    assert "vehicles-put_vehicle" in ids
    assert set(spec["paths"]) == {
        "/api/v1/vehicles",
        "/api/v1/vehicles/{vehicle_id}",
        "/api/v1/vehicles/{vehicle_id}/latest",
        "/api/v1/vehicles/{vehicle_id}/series",
        "/api/v1/vehicles/{vehicle_id}/report",
        "/api/v1/vehicles/{vehicle_id}/slipmap",
        "/api/v1/vehicles/{vehicle_id}/commands/{estimator}/{command}",
        "/api/v1/vehicles/{vehicle_id}/calibration",
        "/api/v1/vehicles/{vehicle_id}/calibration/{estimator}",
        "/api/v1/fleet/report",
        "/api/v1/fleet/slipmap",
        "/api/v1/estimators",
        "/api/v1/alerts",
        "/api/v1/health",
        "/api/v1/metrics",
        "/api/v1/tokens",
        "/api/v1/tokens/{token_id}",
        "/api/v1/dashboard",
    }
    assert spec["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    for path, path_ops in spec["paths"].items():
        for op in path_ops.values():
            assert ("security" in op) == (path != "/api/v1/health"), path
    put = spec["paths"]["/api/v1/vehicles/{vehicle_id}"]["put"]
    body = put["requestBody"]["content"]["application/json"]["schema"]
    for kind in body["oneOf"]:  # one closed object per vehicle kind
        assert kind["additionalProperties"] is False
        assert {"kind", "noise", "slip", "estimators"} <= set(kind["properties"])
    assert (
        "text/csv"
        in spec["paths"]["/api/v1/vehicles/{vehicle_id}/series"]["get"]["responses"]["200"][
            "content"
        ]
    )
    assert client.get("/docs").status_code == 200


def test_routers_are_one_list(tmp_path: Path) -> None:
    extra = APIRouter(prefix="/live", tags=["live"])

    @extra.get("/ping")
    def ping() -> dict[str, str]:
        return {"pong": "yes"}

    settings = make_settings(tmp_path)
    app = create_app(settings, FakeRuntime(settings), routers=[*API_ROUTERS, extra, extra])
    with running(app) as client:
        assert client.get("/api/v1/live/ping").json() == {"pong": "yes"}
        ids = [
            op["operationId"]
            for p in client.get("/openapi.json").json()["paths"].values()
            for op in p.values()
        ]
        assert ids.count("live-ping") == 1


def test_api_docs_need_no_internet(client: ApiClient) -> None:
    """``/docs`` loads Swagger UI from this server, not from a CDN (field servers are offline)."""
    page = client.get("/docs")
    assert page.status_code == 200
    html = page.text
    assert "/docs-assets/swagger-ui-bundle.js" in html and "/docs-assets/swagger-ui.css" in html
    assert "cdn." not in html and "https://" not in html
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        r = client.get(f"/docs-assets/{asset}")
        assert r.status_code == 200 and len(r.content) > 100_000


def test_the_3d_view_route_says_whether_the_view_is_off_or_not_running(tmp_path: Path) -> None:
    """Enabled but not running (the runtime has no viewer port) is 503; disabled is 404."""
    settings = make_settings(tmp_path)
    assert settings.viewer.enabled
    with running(create_app(settings, FakeRuntime(settings))) as client:
        r = client.get("/api/v1/viewer/")
        assert r.status_code == 503 and "not running" in r.json()["reason"]
    settings.viewer.enabled = False
    with running(create_app(settings, FakeRuntime(settings))) as client:
        r = client.get("/api/v1/viewer/")
        assert r.status_code == 404 and "disabled" in r.json()["reason"]
