"""Revoking a token closes its open WebSockets on a real ``slipfleet serve`` with code 1008
(REST ``DELETE /tokens/{id}`` and ``slipfleet token revoke`` from another process), while
another token's sockets keep streaming."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from server.api.deps import WS_BEARER_PROTOCOL
from server.settings import StorageSettings
from server.storage import open_store
from server.tokens import Role, issue_token
from tests.server.faults._harness import REPO, ServerProcess

#: How long a socket is read for its close: a bound for what never comes (the streams send
#: on, every 250-1000 ms, while open), no cost when the close comes at once.
CLOSE_WAIT_S = 30.0


def _tokens(data_dir: Path) -> dict[str, tuple[str, int]]:
    store = open_store(StorageSettings(data_dir=data_dir))
    try:
        out = {}
        for name, role in (("admin", Role.ADMIN), ("v1", Role.VIEWER), ("v2", Role.VIEWER)):
            token, record = issue_token(store, name, role, time.time_ns())
            out[name] = (token, record.id)
        return out
    finally:
        store.close()


def _open(server: ServerProcess, path: str, token: str) -> ClientConnection:
    url = f"ws://127.0.0.1:{server.api_port}{path}"
    ws = connect(url, subprotocols=[WS_BEARER_PROTOCOL, token], open_timeout=10)  # type: ignore[list-item]
    ws.recv(timeout=10)
    return ws


def _close_code(ws: ClientConnection) -> int | None:
    """The code ``ws`` is closed with, read until the close (None: open after
    :data:`CLOSE_WAIT_S`, or closed without a code)."""
    end_s = time.monotonic() + CLOSE_WAIT_S
    try:
        while (left_s := end_s - time.monotonic()) > 0:
            ws.recv(timeout=left_s)
    except ConnectionClosed as exc:
        return exc.rcvd.code if exc.rcvd else None
    except TimeoutError:
        pass
    return None


@pytest.mark.zenoh
def test_revocation_closes_open_websockets(tmp_path: Path) -> None:
    data = tmp_path / "data"
    tokens = _tokens(data)
    server = ServerProcess(tmp_path, extra_env={"SLIPFLEET_API__REQUIRE_AUTH": "true"})
    server.start()
    try:
        server.wait_ready()
        v1 = [
            _open(server, "/api/v1/live/fleet", tokens["v1"][0]),
            _open(server, "/api/v1/live/vehicles/a", tokens["v1"][0]),
        ]
        v2 = _open(server, "/api/v1/live/fleet?interval_ms=250", tokens["v2"][0])
        with server.client() as c:
            admin = {"authorization": f"Bearer {tokens['admin'][0]}"}
            assert c.delete(f"/api/v1/tokens/{tokens['v1'][1]}", headers=admin).status_code == 204
        closed = [_close_code(ws) for ws in v1]
        assert '"type":"fleet"' in v2.recv(timeout=5)  # the other token streams on

        cli = subprocess.run(
            [sys.executable, "-m", "server.cli", "token", "revoke", str(tokens["v2"][1])],
            cwd=REPO,
            env={
                **os.environ,
                **{k: v for k, v in server.env.items() if k.startswith("SLIPFLEET")},
            },
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert cli.returncode == 0, cli.stderr
        closed.append(_close_code(v2))
    finally:
        server.stop()
    assert closed == [1008, 1008, 1008]
