"""Running the real ``slipfleet`` command in a child process, as a user would."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

from server.app_main import ServerThread, build_app
from server.settings import Settings
from tests.support import free_port

__all__ = ["REPO", "cli_env", "run_cli", "serving", "start_cli"]

REPO = Path(__file__).resolve().parents[2]


def cli_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """This checkout first on the path, no settings file or token from the caller's shell."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLIPFLEET_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    env.update(extra or {})
    return env


def run_cli(
    args: Sequence[str],
    env: Mapping[str, str] | None = None,
    timeout_s: float = 120.0,
    cwd: Path | None = None,
) -> subprocess.CompletedProcess[str]:
    """``slipfleet ARGS`` to completion; stdout and stderr captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "server.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=cli_env(env),
        cwd=cwd,
        check=False,
    )


def start_cli(
    args: Sequence[str], env: Mapping[str, str] | None = None, cwd: Path | None = None
) -> subprocess.Popen[str]:
    """``slipfleet ARGS`` started, stdout and stderr piped as text (the caller ends it)."""
    return subprocess.Popen(
        [sys.executable, "-m", "server.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=cli_env(env),
        cwd=cwd,
    )


@contextmanager
def serving(settings: Settings) -> Iterator[Settings]:
    """The whole server of ``settings`` in this process, its REST API on a free port (written
    into ``settings.api.port``), until the block ends."""
    settings.api.port = free_port()
    server = ServerThread(build_app(settings), "127.0.0.1", settings.api.port)
    server.start()
    try:
        yield settings
    finally:
        server.stop()
