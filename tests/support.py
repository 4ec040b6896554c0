"""Small helpers shared by tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from server.tooling.ports import free_port

__all__ = ["VEHICLE_CLIENT", "free_port", "run_vehicle_client"]

#: The runnable vehicle client of ``docs/examples``.
VEHICLE_CLIENT = Path(__file__).resolve().parents[1] / "docs" / "examples" / "vehicle_client.py"


def run_vehicle_client(
    endpoint: str, vehicle_id: str, seconds: float
) -> subprocess.CompletedProcess[str]:
    """Run the example vehicle client against ``endpoint`` for ``seconds``; returns its result."""
    return subprocess.run(
        [
            sys.executable,
            str(VEHICLE_CLIENT),
            "--connect",
            endpoint,
            "--vehicle-id",
            vehicle_id,
            "--seconds",
            str(seconds),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
