"""A ``slipfleet`` server in a child process on loopback, for load tests and benchmarks.

The parent passes the settings as JSON in the environment (the storage URL, a secret, in
``SLIPFLEET_STORAGE__URL``, never in argv); the child, ``python -m
server.tooling.server_process``, runs :func:`server.app_main.serve` with them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from server.tooling.ports import free_port
from server.tooling.procs import stop_process

__all__ = ["ServerProcess"]

_SETTINGS_ENV = "LOADTEST_SERVER_SETTINGS"
_STORAGE_URL_ENV = "SLIPFLEET_STORAGE__URL"


@dataclass
class ServerProcess:
    """A ``slipfleet`` server in a child process on loopback.

    Parameters
    ----------
    settings : dict
        ``Settings`` fields (nested dicts); ``api.port`` and the Zenoh endpoints are filled in
        when missing. The storage URL, a secret, goes through the environment, not argv.
    storage_url : str or None
        PostgreSQL URL; None keeps SQLite in ``data_dir``.
    """

    settings: dict[str, Any]
    storage_url: str | None = None
    log_path: Path | None = None
    proc: subprocess.Popen[bytes] | None = None
    api: str = ""
    endpoint: str = ""

    def start(self, timeout_s: float = 60.0) -> ServerProcess:
        import httpx

        s = json.loads(json.dumps(self.settings))
        s.setdefault("api", {})
        s["api"].setdefault("port", free_port())
        s["api"]["host"] = "127.0.0.1"
        s["api"]["require_auth"] = False
        s.setdefault("viewer", {})["enabled"] = False
        z = s.setdefault("zenoh", {})
        if not z.get("connect"):
            z.setdefault("listen", [f"tcp/127.0.0.1:{free_port()}"])
            self.endpoint = z["listen"][0]
        else:
            self.endpoint = z["connect"][0]
        self.api = f"http://127.0.0.1:{s['api']['port']}"
        env = {**os.environ, _SETTINGS_ENV: json.dumps(s)}
        if self.storage_url:
            env[_STORAGE_URL_ENV] = self.storage_url
        out: IO[bytes] | int = subprocess.DEVNULL
        if self.log_path is not None:
            out = self.log_path.open("ab")
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "server.tooling.server_process"],
                env=env,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        finally:
            if not isinstance(out, int):
                out.close()  # the child has its own descriptor
        deadline = time.monotonic() + timeout_s
        with httpx.Client(base_url=self.api, timeout=2.0) as client:
            while True:
                if self.proc.poll() is not None:
                    raise RuntimeError(f"server exited with {self.proc.returncode} while starting")
                with contextlib.suppress(httpx.HTTPError):
                    if client.get("/api/v1/health").status_code == 200:
                        return self
                if time.monotonic() > deadline:
                    self.stop()
                    raise TimeoutError("server did not become healthy in time")
                time.sleep(0.1)

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def stop(self, timeout_s: float = 60.0) -> int | None:
        """SIGTERM (graceful: the pipeline and writer flush), SIGKILL after ``timeout_s``."""
        if self.proc is None:
            return None
        return stop_process(self.proc, timeout_s)

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _serve_child() -> int:
    """Child entry point: run the server from the JSON settings in the environment."""
    from server.app_main import serve
    from server.settings import Settings

    logging.basicConfig(
        level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    serve(Settings.model_validate(json.loads(os.environ[_SETTINGS_ENV])), log_level="warning")
    return 0


if __name__ == "__main__":
    raise SystemExit(_serve_child())
