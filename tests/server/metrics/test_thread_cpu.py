"""Thread CPU by name: Python threads by their threading name, others by their OS name."""

from __future__ import annotations

import re
import threading
import time

import zenoh

from server.metrics.thread_cpu import thread_cpu_seconds
from server.tooling.router import router_config
from tests.support import free_port


def _spin(cpu_s: float, started: threading.Event, hold: threading.Event) -> None:
    t0 = time.thread_time()
    while time.thread_time() - t0 < cpu_s:
        pass
    started.set()
    hold.wait(10)  # stay alive until measured: an ended thread is no longer listed


def _spinners(
    name: str, count: int, cpu_s: float
) -> tuple[list[threading.Thread], threading.Event]:
    hold = threading.Event()
    threads, done = [], []
    for _ in range(count):
        started = threading.Event()
        t = threading.Thread(target=_spin, args=(cpu_s, started, hold), name=name, daemon=True)
        t.start()
        threads.append(t)
        done.append(started)
    for started in done:
        assert started.wait(30)
    return threads, hold


def test_a_busy_thread_is_charged_under_its_name() -> None:
    before = thread_cpu_seconds().get("cpu-test-busy", 0.0)
    threads, hold = _spinners("cpu-test-busy", 1, 0.3)
    try:
        names = thread_cpu_seconds()
        busy = names["cpu-test-busy"]
    finally:
        hold.set()
        for t in threads:
            t.join()
    assert before == 0.0
    assert 0.25 <= busy <= 1.0
    assert "MainThread" in names, names  # Python's threads go by their threading name
    assert "cpu-test-busy" not in thread_cpu_seconds(), "an ended thread is no longer counted"


def test_threads_of_one_name_add_up() -> None:
    threads, hold = _spinners("cpu-test-pair", 2, 0.2)
    try:
        pair = thread_cpu_seconds()["cpu-test-pair"]
    finally:
        hold.set()
        for t in threads:
            t.join()
    assert pair >= 0.35  # two threads of 0.2 s each (the clock ticks in 10 ms steps)


def test_threads_python_did_not_start_go_by_their_os_name_without_the_pool_index() -> None:
    # a loopback router (no multicast scouting): Zenoh's runtime threads "rx-0", "acc-0", ...
    session = zenoh.open(router_config([f"tcp/127.0.0.1:{free_port()}"]))
    try:
        names = thread_cpu_seconds()
    finally:
        session.close()
    native = [n for n in names if n.startswith("os:")]
    assert native, names
    assert not any(re.search(r"-\d+$", n) for n in native), native
    assert all(seconds >= 0.0 for seconds in names.values())
