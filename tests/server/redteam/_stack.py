"""Helpers of the red-team suite: a real server process's memory and counters, a Zenoh client
on loopback."""

from __future__ import annotations

import json
import re
from pathlib import Path

import httpx
import zenoh

__all__ = ["client_session", "rejected", "rss_bytes"]

_REJECTED = re.compile(
    r'^slipfleet_packets_rejected_total\{vehicle="(?P<v>[^"]*)",reason="(?P<r>[^"]+)"\} (?P<n>\S+)$'
)


def rss_bytes(pid: int) -> tuple[int, int]:
    """``(VmRSS, VmHWM)`` of process ``pid`` in bytes: its resident memory now and at its peak."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            fields[name] = int(value.split()[0]) * 1024
    return fields["VmRSS"], fields["VmHWM"]


def rejected(client: httpx.Client, vehicle_id: str) -> dict[str, int]:
    """A vehicle's refused packets by reason, from ``/api/v1/metrics``."""
    text = client.get("/api/v1/metrics").raise_for_status().text
    out: dict[str, int] = {}
    for line in text.splitlines():
        m = _REJECTED.match(line)
        if m and m["v"] == vehicle_id:
            out[m["r"]] = int(float(m["n"]))
    return out


def client_session(endpoint: str) -> zenoh.Session:
    """A vehicle-like client session on loopback (no scouting)."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)
