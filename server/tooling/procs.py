"""Stopping the child processes of load tests, benchmarks and tests."""

from __future__ import annotations

import subprocess
from typing import Any

__all__ = ["stop_process"]


def stop_process(
    proc: subprocess.Popen[Any], grace_s: float, kill_wait_s: float = 10.0
) -> int | None:
    """SIGTERM ``proc`` (a graceful stop: servers flush), SIGKILL if it is still running after
    ``grace_s``; returns its exit code (None only if it outlived the kill wait too)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(kill_wait_s)
    return proc.returncode
