"""What ``slipfleet serve`` runs: the full app, and the same app on a background thread.

Kept apart from :mod:`server.cli` so the argument parser imports nothing heavy.
"""

from __future__ import annotations

import threading
import time

import uvicorn
from fastapi import FastAPI

from server.api.app import create_app
from server.gc_policy import settle
from server.runtime import Runtime
from server.settings import Settings
from server.web import mount_web

__all__ = ["ServerThread", "build_app", "serve"]


def build_app(settings: Settings) -> FastAPI:
    """The whole server app: REST API, live feeds, dashboard at ``/``; the runtime (opened in the
    app's lifespan) serves them."""
    app = create_app(settings, Runtime(settings))
    mount_web(app)
    return app


def serve(settings: Settings, *, log_level: str = "info") -> None:
    """Run the server until interrupted (this process's collector settled first: see
    :mod:`server.gc_policy`)."""
    app = build_app(settings)
    settle(settings.ingest.gc_gen0)
    uvicorn.run(
        app,
        host=settings.api.host,
        port=settings.api.port,
        log_level=log_level,
        ws="websockets-sansio",
    )


class ServerThread:
    """uvicorn on a background thread; ``start`` returns once the app is up (lifespan done)."""

    def __init__(self, app: FastAPI, host: str, port: int) -> None:
        config = uvicorn.Config(
            app, host=host, port=port, log_level="warning", ws="websockets-sansio"
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def start(self, timeout_s: float = 30.0) -> None:
        self.thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self.thread.is_alive():
                raise RuntimeError("server failed to start (see the log above)")
            if time.monotonic() > deadline:
                raise TimeoutError("server did not start in time")
            time.sleep(0.05)

    @property
    def port(self) -> int:
        sockets = self.server.servers[0].sockets if self.server.servers else []
        return int(sockets[0].getsockname()[1]) if sockets else 0

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(30.0)
