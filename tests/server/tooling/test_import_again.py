"""A log imported a second time into the same vehicle: the store keeps each estimate once, and
``slipfleet import`` says so instead of reporting the second import as if it added the drive
again (a real CSV written by the tests, a real SQLite store, the real command)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from server.cli import main
from server.settings import Settings
from server.storage import open_store
from tests.server.tooling.import_drive import make_drive, write_csv

VEHICLE = "twice"


def _import(path: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert main(["import", str(path), "--vehicle", VEHICLE]) == 0
    return capsys.readouterr().out.strip().splitlines()[-1]


def _stored(data_dir: Path) -> int:
    store = open_store(Settings(storage={"data_dir": data_dir}).storage)
    try:
        return len(store.query_series(VEHICLE, 0, 2**62))
    finally:
        store.close()


def test_a_log_imported_again_is_said_to_add_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "drive.csv"
    write_csv(make_drive(time.time_ns() - 600 * 10**9), path)
    data_dir = tmp_path / "data"
    monkeypatch.setenv("SLIPFLEET_STORAGE__DATA_DIR", str(data_dir))

    first = _import(path, capsys)
    rows = _stored(data_dir)
    assert rows > 300
    assert first.endswith(f"; {rows} estimate rows"), first

    again = _import(path, capsys)
    assert _stored(data_dir) == rows
    assert again.endswith(
        f"; {rows} estimate rows, 0 new: the store held {rows} already "
        "(was this log imported before?)"
    ), again
