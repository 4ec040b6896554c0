"""``slipfleet loadtest --connect`` against a server that requires tokens: without one it stops
with one line before publishing anything; with ``--token-file`` it runs. Real server
in-process (embedded router, SQLite, tokens on); the command in a child process."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.settings import Settings
from server.storage import open_store
from server.tokens import issue_token
from tests.server.cli_support import run_cli, serving
from tests.server.fleet_stack import stack_settings

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


@pytest.fixture
def secured(tmp_path: Path) -> Iterator[tuple[Settings, str]]:
    """A running server that requires tokens, and a viewer token for it."""
    settings = stack_settings(tmp_path, None, 0)
    settings.api.require_auth = True
    store = open_store(settings.storage)
    try:
        token, _ = issue_token(store, "load", "viewer", time.time_ns())
    finally:
        store.close()
    with serving(settings):
        yield settings, token


def _loadtest(
    settings: Settings, *extra: str, env: dict[str, str] | None = None
) -> tuple[int, str, str]:
    args = [
        "loadtest",
        "--vehicles",
        "2",
        "--duration",
        "1",
        "--warmup",
        "0.5",
        "--scenario",
        "field_work",
    ]
    args += [
        "--connect",
        settings.zenoh.listen[0],
        "--api",
        f"http://127.0.0.1:{settings.api.port}",
        *extra,
    ]
    result = run_cli(args, env=env, timeout_s=240)
    assert "Traceback" not in result.stderr, result.stderr
    return result.returncode, result.stdout, result.stderr


def _vehicles(settings: Settings, token: str) -> list[str]:
    r = httpx.get(
        f"http://127.0.0.1:{settings.api.port}/api/v1/vehicles",
        headers={"Authorization": f"Bearer {token}"},
    )
    return [v["vehicle_id"] for v in r.raise_for_status().json()["data"]]


def test_without_a_token_one_line_and_nothing_published(
    secured: tuple[Settings, str], tmp_path: Path
) -> None:
    settings, token = secured
    code, out, err = _loadtest(settings)
    assert code == 1 and out == ""
    assert err.strip().splitlines() == [
        f"the server at http://127.0.0.1:{settings.api.port} requires an access token: pass "
        "--token-file FILE (or set SLIPFLEET_TOKEN) with a viewer token: slipfleet token "
        "create --name tools --role viewer"
    ]
    wrong = tmp_path / "wrong.token"
    wrong.write_text("sft_" + "A" * 43 + "\n")
    code, _, err = _loadtest(settings, "--token-file", str(wrong))
    assert code == 1 and "refused the access token given" in err
    time.sleep(1.0)
    assert _vehicles(settings, token) == []


def test_with_a_token_file_or_variable_it_runs(
    secured: tuple[Settings, str], tmp_path: Path
) -> None:
    settings, token = secured
    path = tmp_path / "viewer.token"
    path.write_text(token + "\n")
    code, out, err = _loadtest(settings, "--token-file", str(path))
    assert code == 0, err
    assert "vehicles 2 (seen 2;" in out
    assert sorted(_vehicles(settings, token)) == ["sim-00001", "sim-00002"]
    code, out, err = _loadtest(settings, env={"SLIPFLEET_TOKEN": token})
    assert code == 0, err
