"""The documented report client runs against a real server fed by the example vehicle client."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.app_main import ServerThread, build_app
from server.settings import Settings
from tests.support import free_port

EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"


def _run(script: str, *args: str) -> str:
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


@pytest.mark.zenoh
def test_report_client_reads_what_the_vehicle_client_sent(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(
        zenoh={"listen": [endpoint]},
        storage={"data_dir": tmp_path, "commit_interval_s": 0.2},
        api={"port": 0, "require_auth": False},
        viewer={"enabled": False},
    )
    server = ServerThread(build_app(settings), "127.0.0.1", 0)
    server.start()
    try:
        _run("vehicle_client.py", "--connect", endpoint, "--vehicle-id", "doc-2", "--seconds", "6")
        time.sleep(1.5)  # lateness window + writer commit interval
        out_csv = tmp_path / "doc-2.csv"
        stdout = _run(
            "report_client.py",
            "--url",
            f"http://127.0.0.1:{server.port}",
            "--csv-vehicle",
            "doc-2",
            "--csv-out",
            str(out_csv),
        )
    finally:
        server.stop()
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["vehicles"] == ["doc-2"]
    assert "doc-2" in stdout.splitlines()[1]  # the table row
    with open(out_csv, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == summary["csv_rows"] and len(rows) >= 20
    # the example vehicle drives at 2 m/s with 5 % slip on the left wheel
    moving = [r for r in rows if r["slip_left_pct"] and float(r["vg_mps"]) > 1.5]
    assert len(moving) >= 10
    slip_left = sorted(float(r["slip_left_pct"]) for r in moving)[len(moving) // 2]
    assert 3.0 < slip_left < 7.0, slip_left
