"""Build the server's Zenoh session from :class:`server.settings.ZenohSettings`.

* ``connect`` empty: the server process *is* the router (``mode: "router"``) listening on
  ``listen`` (loopback by default). No ``zenohd`` binary is needed; vehicles connect to it as
  clients.
* ``connect`` set: the server is a client of those routers.

In both modes multicast scouting is off (endpoints are explicit) and shared memory is off: with
it on, a router refused clients beyond a few hundred, and vehicles never share memory with the
server anyway. ``username``/``password`` are the credentials this session presents to a secured
router (client mode).

Vehicle authentication and ACL (embedded router, or a standalone ``zenohd`` configured by
:func:`router_config_dict` / ``slipfleet zenoh-router-config``):

* ``credentials_file`` is Zenoh's user-password dictionary: one ``user:password`` line per
  vehicle, the user being the vehicle id (blank lines allowed, nothing else). With it set every
  session must present one of these pairs (``transport/auth/usrpwd``), else Zenoh refuses the
  connection. Zenoh reads the passwords in clear, so keep the file ``0600``.
* ``acl`` (on by default) adds ``access_control`` with ``default_permission: deny`` and, per
  vehicle, rules allowing it to publish (``put``) only on its own sensor streams
  (``<key_prefix>/<id>/sensors/<stream>``) and config key, and to subscribe to (and receive) its
  own ``<key_prefix>/<id>/alerts`` and ``.../status``; a deny rule refuses any vehicle's put or
  delete on an alerts or status key, so it cannot forge what the server tells it; every
  vehicle is also told of the server's sensor and config subscriptions (a client publisher
  sends nothing until it knows of a matching subscriber). Anything else a vehicle sends —
  another vehicle's key, a subscription to the fleet — is dropped by the router. The embedded
  router's own session (this server) is not a remote peer, so the ACL does not apply to it; a
  server connecting to a standalone router as ``zenoh.username`` gets a rule to subscribe to
  ``<key_prefix>/**`` and publish alerts.
* Without ``credentials_file`` the embedded router accepts anyone, so it refuses to listen beyond
  loopback unless ``allow_anonymous`` says so.
"""

from __future__ import annotations

import ipaddress
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh

from server.protocol.keys import CONFIG_SUFFIX, SENSORS_CHUNK, is_valid_vehicle_id
from server.settings import ZenohSettings

__all__ = [
    "ROUTER_MAX_SESSIONS",
    "CredentialsError",
    "acl_config",
    "make_config",
    "open_session",
    "read_credential_users",
    "router_config_dict",
]

_log = logging.getLogger(__name__)

#: Vehicles (client sessions) an embedded router accepts; Zenoh's default is 1000.
ROUTER_MAX_SESSIONS = 20_000
#: Connections an embedded router may be opening at once (vehicles reconnecting together).
ROUTER_ACCEPT_PENDING = 2_000


#: Passwords shorter than this in the credentials file are accepted with a warning.
MIN_PASSWORD_CHARS = 16


class CredentialsError(ValueError):
    """The credentials file cannot be used (says which line, never a password)."""


def _insert(config: zenoh.Config, key: str, value: Any) -> None:
    config.insert_json5(key, json.dumps(value))


def read_credential_users(path: Path, *, server_user: str | None = None) -> list[str]:
    """The user names of Zenoh's user-password dictionary at ``path``, in file order.

    Every non-blank line must be ``user:password`` (the password may contain ``:``) with a
    non-empty password, users unique, and each user a vehicle id
    (:func:`server.protocol.keys.is_valid_vehicle_id`) or ``server_user``. Warns when the file
    is readable by group or others, or a password is shorter than :data:`MIN_PASSWORD_CHARS`.

    Raises
    ------
    CredentialsError
        The file is missing, unreadable or has a line that breaks these rules.
    """
    try:
        text = path.read_text(encoding="utf-8")
        mode = path.stat().st_mode
    except (OSError, UnicodeDecodeError) as exc:
        raise CredentialsError(f"zenoh.credentials_file {path}: {exc}") from exc
    if mode & 0o077:
        _log.warning("%s is readable by others (mode %o); chmod 600 it", path, mode & 0o777)
    users: list[str] = []
    short: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        user, password = user.strip(), password.strip()
        where = f"zenoh.credentials_file {path} line {number}"
        if not sep or not user or not password:
            raise CredentialsError(f"{where}: expected user:password")
        if user in users:
            raise CredentialsError(f"{where}: user {user!r} appears twice")
        if user != server_user and not is_valid_vehicle_id(user):
            raise CredentialsError(
                f"{where}: user {user!r} is neither a vehicle id nor zenoh.username"
            )
        if len(password) < MIN_PASSWORD_CHARS:
            short.append(user)
        users.append(user)
    if short:
        _log.warning("zenoh credentials shorter than %d characters: %s", MIN_PASSWORD_CHARS, short)
    return users


def _vehicle_rules(prefix: str, vid: str) -> list[dict[str, Any]]:
    """One vehicle's allow rules: put on its own sensor streams and config, subscribe to and
    receive its own alerts and status."""
    told = [f"{prefix}/{vid}/alerts", f"{prefix}/{vid}/status"]  # what the server tells it
    return [
        {
            "id": f"{vid}/publish",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put"],
            "key_exprs": [f"{prefix}/{vid}/{SENSORS_CHUNK}/*", f"{prefix}/{vid}/{CONFIG_SUFFIX}"],
        },
        {
            "id": f"{vid}/alerts-subscribe",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_subscriber"],
            "key_exprs": told,
        },
        {
            "id": f"{vid}/alerts-receive",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": told,
        },
    ]


def _shared_vehicle_rules(prefix: str) -> list[dict[str, Any]]:
    """Rules every vehicle shares: it is told of the server's subscriptions (a client publisher
    sends only while it knows a matching subscriber, so without this its puts were dropped on
    the vehicle side), and it may never put or delete on any alerts or status key (what the
    server tells vehicles and operators), whatever an allow rule says: a deny wins."""
    return [
        {
            "id": "vehicles/see-server-subscriptions",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["declare_subscriber"],
            "key_exprs": [f"{prefix}/*/{SENSORS_CHUNK}/**", f"{prefix}/*/{CONFIG_SUFFIX}"],
        },
        {
            "id": "vehicles/never-forge-server-keys",
            "permission": "deny",
            "flows": ["ingress"],
            "messages": ["put", "delete"],
            "key_exprs": [f"{prefix}/*/alerts/**", f"{prefix}/*/status/**"],
        },
    ]


def acl_config(
    prefix: str,
    vehicle_ids: list[str],
    server_user: str | None,
    trusted: Sequence[str] = (),
) -> dict[str, Any]:
    """Zenoh ``access_control``: deny by default; each vehicle (matched by its user name) may
    put on its own ``<prefix>/<id>/sensors/<stream>`` and ``<prefix>/<id>/config`` only,
    subscribe to its own ``<prefix>/<id>/alerts`` and ``<prefix>/<id>/status``, and is denied
    any put on an alerts or status key (its own included: those are the server's word);
    ``server_user`` (a server connecting to a standalone router) and the ``trusted`` users
    (server replicas, linked routers) may subscribe to and publish under ``<prefix>/**``."""
    shared = _shared_vehicle_rules(prefix) if vehicle_ids else []
    rules: list[dict[str, Any]] = list(shared)
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for vid in vehicle_ids:
        own = _vehicle_rules(prefix, vid)
        rules += own
        subjects.append({"id": f"vehicle/{vid}", "usernames": [vid]})
        policies.append(
            {
                "rules": [r["id"] for r in own] + [r["id"] for r in shared],
                "subjects": [f"vehicle/{vid}"],
            }
        )
    servers = [u for u in dict.fromkeys([server_user, *trusted]) if u is not None]
    if servers:
        own = _server_rules(prefix)
        rules += own
        subjects.append({"id": "server", "usernames": servers})
        policies.append({"rules": [r["id"] for r in own], "subjects": ["server"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _server_rules(prefix: str) -> list[dict[str, Any]]:
    """A server's rules: subscribe to and put anything under ``<prefix>/**``, both ways."""
    return [
        {
            "id": "server/ingress",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_subscriber", "put"],
            "key_exprs": [f"{prefix}/**"],
        },
        {
            "id": "server/egress",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": [f"{prefix}/**"],
        },
    ]


def _is_loopback(endpoint: str) -> bool:
    """True for ``<proto>/<host>:<port>`` endpoints whose host is a loopback address."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    _, _, address = locator.partition("/")
    host = address.rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _router_entries(settings: ZenohSettings, listen: list[str]) -> dict[str, Any]:
    """Config entries (slash-separated keys) of a router for ``settings`` listening on
    ``listen``: authentication and ACL as the module docstring says."""
    if not listen:
        raise ValueError("zenoh.listen must name at least one endpoint when zenoh.connect is empty")
    entries: dict[str, Any] = {
        "mode": "router",
        "listen/endpoints": list(listen),
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "transport/shared_memory/enabled": False,
        "transport/unicast/max_sessions": ROUTER_MAX_SESSIONS,
        "transport/unicast/accept_pending": ROUTER_ACCEPT_PENDING,
    }
    path = settings.credentials_file
    if path is None:
        if not settings.allow_anonymous and not all(_is_loopback(e) for e in listen):
            raise ValueError(
                "the Zenoh router would accept anyone on a non-loopback endpoint: set "
                "zenoh.credentials_file (vehicle credentials), or zenoh.allow_anonymous"
            )
        return entries
    users = read_credential_users(path, server_user=settings.username)
    entries["transport/auth/usrpwd/dictionary_file"] = str(path.resolve())
    if settings.acl:
        trusted = [u for u in settings.trusted_users if u in users]
        vehicles = [u for u in users if u != settings.username and u not in trusted]
        server_user = settings.username if settings.username in users else None
        entries["access_control"] = acl_config(settings.key_prefix, vehicles, server_user, trusted)
    return entries


def router_config_dict(settings: ZenohSettings, listen: list[str] | None = None) -> dict[str, Any]:
    """A standalone router's config (nested, for ``zenohd -c``) with the vehicle credentials and
    ACL of ``settings``; ``listen`` defaults to ``settings.listen``. The server then connects as
    a client with ``zenoh.username``/``password``, an entry of the same credentials file."""
    nested: dict[str, Any] = {}
    for key, value in _router_entries(settings, list(listen or settings.listen)).items():
        *parents, leaf = key.split("/")
        node = nested
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return nested


def make_config(settings: ZenohSettings) -> zenoh.Config:
    """A Zenoh config for the server: embedded router or client (see module docstring)."""
    config = zenoh.Config()
    if settings.connect:
        _insert(config, "scouting/multicast/enabled", False)
        _insert(config, "transport/shared_memory/enabled", False)
        _insert(config, "mode", "client")
        _insert(config, "connect/endpoints", list(settings.connect))
    else:
        for key, value in _router_entries(settings, list(settings.listen)).items():
            _insert(config, key, value)
    password = _password(settings)
    if settings.username is not None and password is not None:
        _insert(config, "transport/auth/usrpwd/user", settings.username)
        _insert(config, "transport/auth/usrpwd/password", password)
    elif settings.username is not None or password is not None:
        raise ValueError("zenoh.username and zenoh.password (or password_file) go together")
    return config


def _password(settings: ZenohSettings) -> str | None:
    """``zenoh.password``, else the first line of ``zenoh.password_file``, else None."""
    if settings.password is not None:
        return settings.password.get_secret_value()
    if settings.password_file is None:
        return None
    try:
        lines = settings.password_file.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise CredentialsError(f"zenoh.password_file {settings.password_file}: {exc}") from exc
    if not lines or not lines[0].strip():
        raise CredentialsError(f"zenoh.password_file {settings.password_file} is empty")
    return lines[0].strip()


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open the server's session (a context manager; close it on shutdown)."""
    return zenoh.open(make_config(settings))
