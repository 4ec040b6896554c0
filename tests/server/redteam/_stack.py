"""Helpers of the red-team suite: a real server process's memory and counters, a Zenoh client
on loopback."""

from __future__ import annotations

import json
import re
from pathlib import Path

import httpx
import zenoh

from estimator.types import GnssFix, GnssSample
from server.protocol import encode_gnss

__all__ = ["client_session", "gnss_payload", "rejected", "rss_bytes"]

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


def gnss_payload(stamp_ns: int, seq: int) -> bytes:
    """One valid GNSS packet (RTK fix, 1 m/s east) stamped ``stamp_ns``."""
    sample = GnssSample(
        stamp_ns=stamp_ns,
        vel_enu_mps=(1.0, 0.0, 0.0),
        heading_rad=0.0,
        pitch_rad=0.0,
        roll_rad=0.0,
        lat_deg=48.0,
        lon_deg=11.0,
        height_m=500.0,
        fix=GnssFix.RTK_FIXED,
        vel_std_mps=0.02,
    )
    return encode_gnss(sample, seq)
