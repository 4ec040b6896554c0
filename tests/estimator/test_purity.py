"""The estimator package is a pure library: no I/O, transport, web or server imports."""

from __future__ import annotations

import subprocess
import sys

FORBIDDEN = ("zenoh", "fastapi", "sqlite3", "psycopg", "uvicorn", "server", "viser", "msgpack")


def test_estimator_imports_no_io_modules() -> None:
    code = (
        "import sys\n"
        "import estimator, estimator.mdsf, estimator.kalman, estimator.slip, estimator.tilt\n"
        "import estimator.wheel_speed, estimator.reference_speed, estimator.dead_reckoning\n"
        f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
