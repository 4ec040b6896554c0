"""The 3D view has no authentication of its own (viser has none): it listens on loopback only,
and a server told to bind it elsewhere refuses to start unless ``viewer.allow_remote`` says
so. From elsewhere it is reached through the API's origin (``/api/v1/viewer``), behind the same
tokens as REST."""

from __future__ import annotations

import ipaddress
import os
import socket
import time
from pathlib import Path

import pytest
import viser
import zstandard
from pydantic import ValidationError
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from server.api.routes.viewer import VIEWER_COOKIE
from server.settings import StorageSettings, ViewerSettings
from server.storage import open_store
from server.tokens import Role, issue_token
from server.tooling.bench.live import CHROMIUM_ARGS
from tests.server.faults._harness import Publisher, ServerProcess, wait_until
from tests.support import free_port


def _listening(port: int) -> list[ipaddress.IPv4Address | ipaddress.IPv6Address]:
    """Local addresses with a TCP socket listening on ``port`` (from /proc/net/tcp, tcp6)."""
    out: list[ipaddress.IPv4Address | ipaddress.IPv6Address] = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr_hex, port_hex = local.split(":")
            if state != "0A" or int(port_hex, 16) != port:
                continue
            raw = bytes.fromhex(addr_hex)
            # the kernel prints each 32-bit word in host (little-endian) order
            words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            out.append(ipaddress.ip_address(words))
    return out


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "10.1.2.3", "viewer.example"])
def test_a_non_loopback_viewer_host_is_refused_without_opt_in(host: str) -> None:
    with pytest.raises(ValidationError, match="no authentication"):
        ViewerSettings(host=host)
    assert ViewerSettings(host=host, allow_remote=True).host == host
    assert not ViewerSettings(host=host, enabled=False).enabled
    for loopback in ("127.0.0.1", "::1", "localhost"):
        assert ViewerSettings(host=loopback).host == loopback


@pytest.mark.zenoh
def test_serve_refuses_a_remote_viewer_and_binds_loopback_by_default(tmp_path: Path) -> None:
    refused = ServerProcess(
        tmp_path,
        extra_env={"SLIPFLEET_VIEWER__ENABLED": "true", "SLIPFLEET_VIEWER__HOST": "0.0.0.0"},
        name="refused",
    )
    refused.start()
    try:
        assert refused.wait_exit(60) != 0
    finally:
        refused.stop()
    assert "no authentication" in refused.log_path.read_text()

    port = free_port()
    server = ServerProcess(
        tmp_path,
        extra_env={"SLIPFLEET_VIEWER__ENABLED": "true", "SLIPFLEET_VIEWER__PORT": str(port)},
    )
    server.start()
    try:
        server.wait_ready()
        wait_until(lambda: _listening(port), 30, "the viewer listening")
        addresses = _listening(port)
        socket.create_connection(("127.0.0.1", port), 5).close()
    finally:
        server.stop()
    assert addresses and all(a.is_loopback for a in addresses), addresses


# ----------------------------------------------------------------------------- through the API

VIEWER_CLOSE_WITHIN_S = 1.5
CHROMIUM = os.environ.get("SLIPFLEET_CHROMIUM", "/usr/bin/chromium")


def _viewer_tokens(data_dir: Path) -> dict[str, tuple[str, int]]:
    store = open_store(StorageSettings(data_dir=data_dir))
    try:
        out = {}
        for name, role in (("admin", Role.ADMIN), ("watcher", Role.VIEWER)):
            token, record = issue_token(store, name, role, time.time_ns())
            out[name] = (token, record.id)
        return out
    finally:
        store.close()


def _viewer_server(tmp_path: Path) -> ServerProcess:
    """A ``slipfleet serve`` started with tokens on and its 3D view on a free loopback port."""
    server = ServerProcess(
        tmp_path,
        extra_env={
            "SLIPFLEET_API__REQUIRE_AUTH": "true",
            "SLIPFLEET_VIEWER__ENABLED": "true",
            "SLIPFLEET_VIEWER__PORT": str(free_port()),
        },
    )
    server.start()
    return server


def _viser_socket(server: ServerProcess, headers: dict[str, str]) -> ClientConnection:
    return connect(
        f"ws://127.0.0.1:{server.api_port}/api/v1/viewer",
        subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
        additional_headers=headers,
        open_timeout=10,
        max_size=None,
    )


def _messages_of(frame: bytes) -> bytes:
    """The msgpack messages of one viser frame: ``[u64 decompressed size][u64 compressed
    size][zstd msgpack]…`` (the binary buffers after it are left out)."""
    decompressed = int.from_bytes(frame[:8], "little")
    compressed = int.from_bytes(frame[8:16], "little")
    body = zstandard.ZstdDecompressor().decompress(
        frame[16 : 16 + compressed], max_output_size=decompressed
    )
    return bytes(body)


def _frames_until(ws: ClientConnection, needle: bytes, timeout_s: float) -> bool:
    """Read viser's frames until one's messages hold ``needle`` (True) or ``timeout_s``
    passes."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            frame = ws.recv(timeout=max(0.1, deadline - time.monotonic()))
        except TimeoutError:
            return False
        if isinstance(frame, bytes) and needle in _messages_of(frame):
            return True
    return False


def _refused_handshake(server: ServerProcess, headers: dict[str, str]) -> int:
    with pytest.raises(InvalidStatus) as refused:
        _viser_socket(server, headers).close()
    return refused.value.response.status_code


@pytest.mark.zenoh
def test_the_3d_view_through_the_api_needs_a_token(tmp_path: Path) -> None:
    """A real server with its viser 3D view on loopback and one simulated vehicle: the view
    reached through the API's origin answers 401 (page) and refuses the WebSocket without a
    valid token or from another origin; with a viewer token the page is served and the socket
    relays the scene (the vehicle's id in it); revoking the token closes that socket."""
    tokens = _viewer_tokens(tmp_path / "data")
    server = _viewer_server(tmp_path)
    publisher = Publisher(server.zenoh_listen, n_vehicles=1, duration_s=30.0, id_prefix="view")
    token, token_id = tokens["watcher"]
    try:
        server.wait_ready()
        publisher.start()
        with server.client() as c:
            assert c.get("/api/v1/viewer/").status_code == 401
            assert c.get("/api/v1/viewer/", params={"token": "sf_" + "x" * 40}).status_code == 401
            moved = c.get("/api/v1/viewer/", params={"token": token})
            assert moved.status_code == 303 and moved.headers["location"] == "/api/v1/viewer/"
            cookie = moved.cookies["slipfleet_viewer"]
            assert "httponly" in moved.headers["set-cookie"].lower()
        with server.client() as c:  # a fresh jar: one way of presenting the token at a time
            page = c.get("/api/v1/viewer/", headers={"cookie": f"slipfleet_viewer={cookie}"})
            assert page.status_code == 200 and "<html" in page.text.lower(), page.status_code
            bearer = c.get("/api/v1/viewer/", headers={"authorization": f"Bearer {token}"})
            assert bearer.status_code == 200 and bearer.content == page.content

        origin = f"http://127.0.0.1:{server.api_port}"
        own = {"Cookie": f"slipfleet_viewer={cookie}", "Origin": origin}
        assert _refused_handshake(server, {"Origin": origin}) == 403
        assert _refused_handshake(server, {**own, "Cookie": "slipfleet_viewer=sf_bad"}) == 403
        assert _refused_handshake(server, {**own, "Origin": "http://evil.example"}) == 403
        ws = _viser_socket(server, own)
        assert _frames_until(ws, b"view-1", 60), "the vehicle never appeared in the 3D view"
        with server.client() as c:
            admin = {"authorization": f"Bearer {tokens['admin'][0]}"}
            assert c.delete(f"/api/v1/tokens/{token_id}", headers=admin).status_code == 204
        t0 = time.monotonic()
        with pytest.raises(ConnectionClosed) as closed:
            while time.monotonic() - t0 < 10:
                ws.recv(timeout=10)
        closed_after_s = time.monotonic() - t0
        assert _refused_handshake(server, own) == 403
    finally:
        publisher.stop()
        server.stop()
    print(f"viewer socket closed {closed_after_s:.2f} s after revocation")
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    assert closed_after_s < VIEWER_CLOSE_WITHIN_S


@pytest.mark.zenoh
@pytest.mark.browser
def test_a_real_browser_gets_the_3d_view_only_with_a_token(tmp_path: Path) -> None:
    """Headless Chromium against a real server: without a token, or with a forged cookie, the
    3D view answers 401; with a viewer token in the link the page is served (viser's client)
    and its own WebSocket, opened from the page with the cookie, is accepted."""
    from playwright.sync_api import sync_playwright

    token, _ = _viewer_tokens(tmp_path / "data")["watcher"]
    server = _viewer_server(tmp_path)
    view = f"{server.base_url}/api/v1/viewer/"
    try:
        server.wait_ready()
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=CHROMIUM, args=list(CHROMIUM_ARGS), headless=True
            )
            try:
                refused = browser.new_context().new_page().goto(view)
                assert refused is not None and refused.status == 401
                forged = browser.new_context()
                forged.add_cookies([{"name": VIEWER_COOKIE, "value": "sft_x", "url": view}])
                refused = forged.new_page().goto(view)
                assert refused is not None and refused.status == 401
                watcher = browser.new_context().new_page()
                answer = watcher.goto(f"{view}?token={token}")
                assert answer is not None and answer.status == 200 and watcher.url == view
                assert watcher.title() == "Viser"
                wait_until(lambda: _socket_accepted(server), 30, "the page's viewer socket")
            finally:
                browser.close()
    finally:
        server.stop()


def _socket_accepted(server: ServerProcess) -> bool:
    """True once the server's access log shows the 3D view's WebSocket accepted."""
    return '"WebSocket /api/v1/viewer" [accepted]' in server.log_path.read_text()
