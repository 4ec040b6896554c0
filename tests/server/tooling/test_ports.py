import socket

import pytest

from server.tooling import ports
from server.tooling.ports import LOWEST_PORT, _ephemeral_low, free_port


def test_ports_are_never_handed_out_twice_and_bind() -> None:
    handed = [free_port() for _ in range(300)]
    assert len(set(handed)) == len(handed)
    for port in handed[:20]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", port))


def test_ports_stay_below_the_kernels_ephemeral_range() -> None:
    high = _ephemeral_low()
    assert all(LOWEST_PORT <= free_port() < high for _ in range(50))


def test_a_port_someone_listens_on_is_skipped(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        busy_port = busy.getsockname()[1]
        other = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        other.bind(("127.0.0.1", 0))
        free = other.getsockname()[1]
        other.close()
        picks = iter([busy_port, free])
        monkeypatch.setattr(ports._rng, "randrange", lambda lo, hi: next(picks))
        assert ports.free_port() == free
