"""Free loopback ports for the embedded services of benchmarks, load tests and tests.

A port from ``bind(("127.0.0.1", 0))`` is free only until the socket closes: the next such call
may hand out the same number (a load test once gave its API and its Zenoh listener one port and
the server exited at start), and every outgoing connection the kernel opens takes its local port
from the same ephemeral range. So :func:`free_port` picks below the kernel's ephemeral range,
never hands out a port twice in one process, and checks that the port binds.
"""

from __future__ import annotations

import random
import socket
import threading
from pathlib import Path

__all__ = ["free_port"]

#: Lowest port handed out; registered services sit mostly below this.
LOWEST_PORT = 20000
_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_DEFAULT_EPHEMERAL_LOW = 32768
_handed_out: set[int] = set()
_lock = threading.Lock()
_rng = random.Random()


def _ephemeral_low() -> int:
    """First port of the kernel's ephemeral range (32768 where the range cannot be read)."""
    try:
        low = int(_RANGE_FILE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return _DEFAULT_EPHEMERAL_LOW
    return low if low > LOWEST_PORT + 1000 else _DEFAULT_EPHEMERAL_LOW


def _binds(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A TCP port on 127.0.0.1 that binds now and that this process has not handed out before.

    Raises
    ------
    RuntimeError
        No such port was found in the range below the ephemeral ports.
    """
    high = _ephemeral_low()
    with _lock:
        for _ in range(1000):
            port = _rng.randrange(LOWEST_PORT, high)
            if port in _handed_out or not _binds(port):
                continue
            _handed_out.add(port)
            return port
    raise RuntimeError(f"no free loopback port in {LOWEST_PORT}-{high - 1}")
