"""deploy/compose.yaml brought up without containers: its two routers and two replicas as the
same processes with the same commands, environment and secrets (ports moved to free ones on
this machine, services' names to 127.0.0.1, each replica on SQLite in place of the shared
PostgreSQL, ingest in-process). The routers listen on 0.0.0.0 as written, so they start only
with the credentials file; router-b logs in to router-a, each replica to its router, each
replica receives its own share's vehicles and only those, and a wrong password is refused."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from server.protocol import sensor_key
from server.protocol.keys import Stream
from tests.server.faults._harness import REPO, ServerProcess, wait_until
from tests.server.redteam._stack import gnss_payload
from tests.support import free_port

COMPOSE = REPO / "deploy" / "compose.yaml"
USERS = ("a-1", "b-1", "server-a", "server-b", "router-b")


def _secrets(tmp: Path) -> dict[str, Path]:
    """The compose file's secrets, written where its ``file:`` entries say (under ``tmp``)."""
    passwords = {u: f"{u}-password-0123456789" for u in USERS}
    files = {}
    for name, spec in yaml.safe_load(COMPOSE.read_text())["secrets"].items():
        path = tmp / spec["file"]
        path.parent.mkdir(parents=True, exist_ok=True)
        if name == "zenoh_credentials":
            path.write_text("".join(f"{u}:{p}\n" for u, p in passwords.items()))
        else:
            user = re.sub(r"_password$", "", name).replace("_", "-")
            path.write_text(passwords[user] + "\n")
        path.chmod(0o600)
        files[name] = path
    return files


def _env(
    service: dict[str, Any], secrets: dict[str, Path], ports: dict[str, int]
) -> dict[str, str]:
    """A service's environment with secrets' paths, names and ports of this machine."""
    out = {}
    for key, value in (service.get("environment") or {}).items():
        value = str(value)
        for name, path in secrets.items():
            value = value.replace(f"/run/secrets/{name}", str(path))
        for host, port in ports.items():
            value = value.replace(f"{host}:7447", f"127.0.0.1:{port}")
        out[key] = value.replace("$$", "$")
    return out


def _router(
    service: dict[str, Any], env: dict[str, str], ports: dict[str, int], own: int, log: Path
) -> subprocess.Popen[bytes]:
    argv = [str(a).replace("0.0.0.0:7447", f"0.0.0.0:{own}") for a in service["command"]]
    for host, port in ports.items():
        argv = [a.replace(f"{host}:7447", f"127.0.0.1:{port}") for a in argv]
    assert argv[:3] == ["python", "-m", "server.tooling.router"]
    with open(log, "wb") as out:
        return subprocess.Popen(
            [sys.executable, *argv[1:]],
            cwd=REPO,
            env={**os.environ, **env},
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def _client(endpoint: str, user: str, password: str) -> zenoh.Session:
    config = zenoh.Config()
    for key, value in {
        "mode": "client",
        "connect/endpoints": [endpoint],
        "scouting/multicast/enabled": False,
        "transport/auth/usrpwd/user": user,
        "transport/auth/usrpwd/password": password,
    }.items():
        config.insert_json5(key, json.dumps(value))
    return zenoh.open(config)


def _received(server: ServerProcess) -> dict[str, int]:
    with server.client() as c:
        text = c.get("/api/v1/metrics").text
    return {
        m[1]: int(float(m[2]))
        for m in re.finditer(
            r'^slipfleet_packets_received_total\{vehicle="([^"]*)"\} (\S+)$', text, re.M
        )
    }


@pytest.mark.zenoh
@pytest.mark.slow
def test_the_compose_layout_starts_as_written(tmp_path: Path) -> None:
    services = yaml.safe_load(COMPOSE.read_text())["services"]
    secrets = _secrets(tmp_path / "deploy")
    ports = {"zenoh-router-a": free_port(), "zenoh-router-b": free_port()}
    procs = []
    servers: dict[str, ServerProcess] = {}
    try:
        for name in ("zenoh-router-a", "zenoh-router-b"):
            env = _env(services[name], secrets, ports)
            log = tmp_path / f"{name}.log"
            procs.append(_router(services[name], env, ports, ports[name], log))
            wait_until(lambda log=log: "listening" in log.read_text(), 30, f"{name} up")
        for name in ("server-a", "server-b"):
            env = _env(services[name], secrets, ports)
            env.pop("SLIPFLEET_STORAGE__URL")  # SQLite here; the shared database is not the point
            env["SLIPFLEET_INGEST__WORKERS"] = "0"
            server = servers[name] = ServerProcess(tmp_path / name, extra_env=env, name=name)
            (tmp_path / name).mkdir()
            server.env.pop("SLIPFLEET_ZENOH__LISTEN", None)
            server.start()
        for server in servers.values():
            server.wait_ready()
        password = {u: f"{u}-password-0123456789" for u in USERS}
        with pytest.raises(zenoh.ZError):
            _client(f"tcp/127.0.0.1:{ports['zenoh-router-a']}", "a-1", "wrong-password-0123")
        now = time.time_ns()
        for vid, router in (("a-1", "zenoh-router-a"), ("b-1", "zenoh-router-b")):
            with _client(f"tcp/127.0.0.1:{ports[router]}", vid, password[vid]) as session:
                pub = session.declare_publisher(
                    sensor_key("fleet", vid, Stream.GNSS),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                time.sleep(1.0)
                for seq in range(5):
                    pub.put(gnss_payload(now + seq * 100_000_000, seq))
                time.sleep(0.5)
        wait_until(lambda: _received(servers["server-a"]).get("a-1") == 5, 30, "a-1 at server-a")
        wait_until(lambda: _received(servers["server-b"]).get("b-1") == 5, 30, "b-1 at server-b")
        assert "b-1" not in _received(servers["server-a"])
        assert "a-1" not in _received(servers["server-b"])
    finally:
        for server in servers.values():
            server.stop()
        for proc in procs:
            proc.terminate()
            proc.wait(30)
