"""A standalone Zenoh router for vehicles and several server replicas.

::

    python -m server.tooling.router --listen tcp/127.0.0.1:7447 [--listen ...] [--connect ENDPOINT]
                                    [--credentials-file PATH]

Vehicles connect to it as clients; each server replica connects with ``zenoh.connect`` set and
subscribes to its own share of the fleet (``zenoh.vehicle_filter``). The configuration is the
server's embedded-router one (:func:`server.ingest.zenoh_session.make_config`): multicast
scouting and shared memory off, room for many client sessions. ``--connect`` links routers to
each other (one router per site, meshed). Runs until SIGINT/SIGTERM.

Credentials and ACL come from the ``zenoh`` settings (``SLIPFLEET_ZENOH__*`` variables or
``SLIPFLEET_CONFIG``), as for the server's embedded router: ``credentials_file`` (vehicles,
replicas and linked routers log in with an entry of it; required to listen beyond loopback
unless ``allow_anonymous``), ``acl``, ``trusted_users`` (the entries that are replicas or
linked routers) and, for a router that links to a secured one with ``--connect``,
``username``/``password``. ``--credentials-file`` overrides the setting's file.
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import zenoh

from server.ingest.zenoh_session import make_config
from server.settings import ZenohSettings, load_settings

__all__ = ["main", "router_config"]


def router_config(
    listen: Sequence[str], connect: Sequence[str] = (), settings: ZenohSettings | None = None
) -> zenoh.Config:
    """Router-mode config listening on ``listen``, optionally linked to other routers, with the
    credentials and ACL of ``settings`` (default: none, loopback only)."""
    base = settings or ZenohSettings()
    config = make_config(base.model_copy(update={"listen": list(listen), "connect": []}))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server.tooling.router", description=__doc__)
    parser.add_argument(
        "--listen", action="append", default=None, help="endpoint (repeatable), default loopback"
    )
    parser.add_argument("--connect", action="append", default=[], help="peer router endpoint")
    parser.add_argument(
        "--credentials-file",
        type=Path,
        default=None,
        help="user:password lines (vehicles, replicas, linked routers); default: "
        "zenoh.credentials_file from the settings",
    )
    args = parser.parse_args(argv)
    listen = args.listen or ["tcp/127.0.0.1:7447"]
    settings = load_settings().zenoh
    if args.credentials_file is not None:
        settings = settings.model_copy(update={"credentials_file": args.credentials_file})
    stop = threading.Event()

    def _on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    with zenoh.open(router_config(listen, args.connect, settings)):
        print(f"zenoh router listening on {', '.join(listen)}", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
