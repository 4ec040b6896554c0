"""The 3D view has no authentication of its own (viser has none): it listens on loopback only,
and a server told to bind it elsewhere refuses to start unless ``viewer.allow_remote`` says
so."""

from __future__ import annotations

import ipaddress
import socket
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.settings import ViewerSettings
from tests.server.faults._harness import ServerProcess, wait_until
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
