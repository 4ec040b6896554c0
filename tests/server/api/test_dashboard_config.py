"""``/dashboard``: the basemap's tile URL reaches the page only when configured."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from server.api import create_app
from server.settings import ApiSettings

from .conftest import ApiClient, FakeRuntime, make_settings, running

TILES = "https://tiles.example.org/{z}/{x}/{y}.png"


def test_no_basemap_by_default(client: ApiClient) -> None:
    r = client.get("/api/v1/dashboard")
    assert r.status_code == 200
    assert r.json() == {"map_tile_url": None}


def test_the_configured_tile_url_is_served(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, map_tile_url=TILES)
    with running(create_app(settings, FakeRuntime(settings))) as client:
        assert client.get("/api/v1/dashboard").json() == {"map_tile_url": TILES}


def test_the_route_needs_a_viewer_token_when_tokens_are_on(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, require_auth=True, map_tile_url=TILES)
    with running(create_app(settings, FakeRuntime(settings))) as client:
        assert client.get("/api/v1/dashboard").status_code == 401


@pytest.mark.parametrize(
    "bad", ["https://tiles.example.org/{z}/{x}.png", "file:///tiles/{z}/{x}/{y}.png"]
)
def test_a_tile_url_without_its_placeholders_or_scheme_is_refused(bad: str) -> None:
    with pytest.raises(ValidationError, match="map_tile_url"):
        ApiSettings(map_tile_url=bad)


def test_the_tile_url_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from server.settings import load_settings

    monkeypatch.setenv("SLIPFLEET_API__MAP_TILE_URL", TILES)
    assert load_settings().api.map_tile_url == TILES
