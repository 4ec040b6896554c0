"""``slipfleet token create | list | revoke`` against a real SQLite file, and the token it prints
opening the REST API."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from server.cli import main
from server.settings import ApiSettings, Settings, StorageSettings
from server.storage import open_store
from server.tokens import hash_token, is_well_formed
from tests.server.api.conftest import FakeRuntime, running


@pytest.fixture
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.delenv("SLIPFLEET_CONFIG", raising=False)
    monkeypatch.setenv("SLIPFLEET_STORAGE__DATA_DIR", str(tmp_path / "data"))
    return tmp_path / "data"


def test_token_create_list_revoke(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["token", "create", "--name", "ops desk", "--role", "operator"]) == 0
    out, err = capsys.readouterr()
    token = out.strip()
    assert is_well_formed(token)
    assert "only" in err and "once" in err

    db = data_dir / "slipfleet.sqlite"
    with sqlite3.connect(db) as conn:
        rows = conn.execute("SELECT id, name, role, token_sha256 FROM api_tokens").fetchall()
    assert rows == [(1, "ops desk", "operator", hash_token(token))]

    assert main(["token", "list"]) == 0
    out, _ = capsys.readouterr()
    assert "ops desk" in out and "operator" in out and "valid" in out and "never" in out
    assert token not in out

    # the printed token opens the API of a server on the same file
    settings = Settings(
        storage=StorageSettings.model_validate({"data_dir": data_dir}),
        api=ApiSettings.model_validate({"require_auth": True}),
    )
    from server.api import create_app

    with running(create_app(settings, FakeRuntime(settings))) as client:
        auth = {"Authorization": f"Bearer {token}"}
        assert client.put("/api/v1/vehicles/t1", json={}, headers=auth).status_code == 201
        assert client.delete("/api/v1/vehicles/t1", headers=auth).status_code == 403

        assert main(["token", "revoke", "1"]) == 0
        assert "revoked token 1" in capsys.readouterr().out
        assert client.get("/api/v1/vehicles", headers=auth).status_code == 401

    assert main(["token", "list"]) == 0
    assert "revoked" in capsys.readouterr().out
    assert main(["token", "revoke", "7"]) == 1
    assert "no token with id 7" in capsys.readouterr().err


def test_token_create_refuses_unknown_roles_and_empty_names(data_dir: Path) -> None:
    for argv in (
        ["token", "create", "--name", "x", "--role", "root"],
        ["token", "create", "--name", "  ", "--role", "viewer"],
        ["token", "revoke", "0"],
    ):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    store = open_store(StorageSettings.model_validate({"data_dir": data_dir}))
    try:
        assert store.list_tokens() == []
    finally:
        store.close()


def test_token_create_expires_in(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import time

    before_ns = time.time_ns()
    assert (
        main(["token", "create", "--name", "shift", "--role", "viewer", "--expires-in", "8h"]) == 0
    )
    out, err = capsys.readouterr()
    assert "expires 20" in err
    assert (
        main(["token", "create", "--name", "gone", "--role", "viewer", "--expires-in", "1s"]) == 0
    )
    capsys.readouterr()
    store = open_store(StorageSettings.model_validate({"data_dir": data_dir}))
    try:
        record = store.get_token(hash_token(out.strip()))
    finally:
        store.close()
    assert record is not None and record.expires_ns is not None
    lifetime_ns = record.expires_ns - before_ns
    assert 8 * 3600 * 10**9 <= lifetime_ns < 8 * 3600 * 10**9 + 60 * 10**9
    time.sleep(1.05)
    assert main(["token", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "valid" in next(x for x in lines if x.endswith("shift"))
    assert "expired" in next(x for x in lines if x.endswith("gone"))


@pytest.mark.parametrize("lifetime", ["0s", "8", "-1h", "1y", "1.5h", "600w", "h"])
def test_token_create_refuses_bad_lifetimes(data_dir: Path, lifetime: str) -> None:
    argv = ["token", "create", "--name", "x", "--role", "viewer", "--expires-in", lifetime]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
