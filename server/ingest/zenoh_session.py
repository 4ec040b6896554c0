"""Build the server's Zenoh session from :class:`server.settings.ZenohSettings`.

* ``connect`` empty: the server process *is* the router (``mode: "router"``) listening on
  ``listen`` (loopback by default). No ``zenohd`` binary is needed; vehicles connect to it as
  clients.
* ``connect`` set: the server is a client of those routers.

In both modes multicast scouting is off (endpoints are explicit) and shared memory is off: with
it on, a router refused clients beyond a few hundred, and vehicles never share memory with the
server anyway. ``username``/``password`` are the credentials this session presents to a secured
router (client mode); the embedded router does not authenticate vehicles, so keep it on
loopback or behind a secured router.
"""

from __future__ import annotations

import json
from typing import Any

import zenoh

from server.settings import ZenohSettings

__all__ = ["ROUTER_MAX_SESSIONS", "make_config", "open_session"]

#: Vehicles (client sessions) an embedded router accepts; Zenoh's default is 1000.
ROUTER_MAX_SESSIONS = 20_000
#: Connections an embedded router may be opening at once (vehicles reconnecting together).
ROUTER_ACCEPT_PENDING = 2_000


def _insert(config: zenoh.Config, key: str, value: Any) -> None:
    config.insert_json5(key, json.dumps(value))


def make_config(settings: ZenohSettings) -> zenoh.Config:
    """A Zenoh config for the server: embedded router or client (see module docstring)."""
    config = zenoh.Config()
    _insert(config, "scouting/multicast/enabled", False)
    _insert(config, "transport/shared_memory/enabled", False)
    if settings.connect:
        _insert(config, "mode", "client")
        _insert(config, "connect/endpoints", list(settings.connect))
    else:
        if not settings.listen:
            raise ValueError(
                "zenoh.listen must name at least one endpoint when zenoh.connect is empty"
            )
        _insert(config, "mode", "router")
        _insert(config, "listen/endpoints", list(settings.listen))
        _insert(config, "scouting/gossip/enabled", False)
        _insert(config, "transport/unicast/max_sessions", ROUTER_MAX_SESSIONS)
        _insert(config, "transport/unicast/accept_pending", ROUTER_ACCEPT_PENDING)
    if settings.username is not None and settings.password is not None:
        _insert(config, "transport/auth/usrpwd/user", settings.username)
        _insert(config, "transport/auth/usrpwd/password", settings.password.get_secret_value())
    elif settings.username is not None or settings.password is not None:
        raise ValueError("zenoh.username and zenoh.password go together")
    return config


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open the server's session (a context manager; close it on shutdown)."""
    return zenoh.open(make_config(settings))
