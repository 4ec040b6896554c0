"""Serve the static dashboard (``web/``) at ``/``.

Call :func:`mount_web` after every API router is included: a mount at ``/`` matches every path,
so it must be the app's last route. Nothing is built: ``web/`` holds plain ES modules and the
vendored uPlot (``web/vendor/``, see its README for the version and licence).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

__all__ = ["WEB_DIR", "mount_web"]

#: The dashboard's files in a source checkout (``<repo>/web``).
WEB_DIR = Path(__file__).resolve().parents[1] / "web"


def mount_web(app: FastAPI, directory: Path | None = None) -> None:
    """Serve ``directory`` (default :data:`WEB_DIR`) at ``/``, ``index.html`` for ``/``."""
    root = directory or WEB_DIR
    if not (root / "index.html").is_file():
        raise FileNotFoundError(f"dashboard not found: {root / 'index.html'}")
    app.mount("/", StaticFiles(directory=root, html=True), name="web")
