"""``slipfleet replay`` beside the vehicle a recording came from (``--as``, ``--shift``), saying
honestly what the server made of the packets, and ``slipfleet record --live`` writing what a
real server's router delivers. A real server (embedded router, SQLite) in-process; the command
in a child process."""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.protocol import decode
from server.protocol.recording import read_recording
from server.settings import Settings
from server.tooling.fleet_commands import record, vehicle_session
from server.tooling.fleet_sim import replay as publish_recording
from tests.server.cli_support import run_cli, serving, start_cli
from tests.server.fleet_stack import stack_settings
from tests.support import poll_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Settings]:
    with serving(stack_settings(tmp_path_factory.mktemp("server"), None, 0)) as settings:
        yield settings


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of one simulated vehicle, sim-0001, 4 s of field work."""
    path = tmp_path_factory.mktemp("rec") / "drive.sfrec"
    record(path, vehicles=1, scenario="field_work", duration_s=4.0)
    return path


def _replay(settings: Settings, path: Path, *extra: str) -> tuple[int, str]:
    args = ["replay", str(path), "--rate", "8", "--connect", settings.zenoh.listen[0]]
    args += ["--api", f"http://127.0.0.1:{settings.api.port}", *extra]
    result = run_cli(args, timeout_s=120)
    assert "Traceback" not in result.stderr, result.stderr
    return result.returncode, result.stdout + result.stderr


def _packets(path: Path) -> int:
    return sum(1 for r in read_recording(path) if "/sensors/" in r.key)


def test_replay_twice_is_told_duplicate_then_accepted_beside_it(
    server: Settings, drive: Path
) -> None:
    n = _packets(drive)
    code, out = _replay(server, drive, "--as", "field-a")
    assert code == 0, out
    assert f"published {n} packets of field-a" in out
    assert f"received {n} of them: {n} accepted, 0 late, 0 duplicate, 0 rejected" in out

    # the same recording under the same id again: the server has these sequence numbers
    code, out = _replay(server, drive, "--as", "field-a")
    assert code == 1, out
    assert f"0 accepted, 0 late, {n} duplicate" in out
    assert "--as NEW_ID" in out and "already has packets of field-a" in out

    # beside it, under another id, shifted to now again: all accepted
    code, out = _replay(server, drive, "--as", "field-b", "--shift", "auto")
    assert code == 0, out
    assert f"{n} accepted" in out
    ids = {
        v["vehicle_id"]
        for v in httpx.get(f"http://127.0.0.1:{server.api.port}/api/v1/vehicles").json()["data"]
    }
    assert {"field-a", "field-b"} <= ids and "sim-0001" not in ids


def _stored_span_ns(
    settings: Settings, vehicle_id: str, start_ns: int, end_ns: int, wait_s: float = 20.0
) -> list[int]:
    """Stamps of the rows stored in the range, waiting up to ``wait_s`` for the first."""
    url = f"http://127.0.0.1:{settings.api.port}/api/v1/vehicles/{vehicle_id}/series"
    deadline = time.monotonic() + wait_s
    while True:
        body = httpx.get(url, params={"start": start_ns, "end": end_ns, "fields": "flags"}).json()
        stamps = body.get("columns", {}).get("stamp_ns", [])
        if stamps or time.monotonic() > deadline:
            return [int(s) for s in stamps]
        time.sleep(0.5)


def test_shift_by_seconds_moves_the_stamps_by_that_much(server: Settings, drive: Path) -> None:
    first_ns = next(iter(read_recording(drive))).stamp_ns
    shift_ns = -3_600 * 10**9
    code, out = _replay(server, drive, "--as", "field-c", "--shift", "-3600")
    assert code == 0, out
    lo, hi = first_ns + shift_ns - 10**9, first_ns + shift_ns + 10 * 10**9
    stamps = _stored_span_ns(server, "field-c", lo, hi)
    assert len(stamps) > 10
    # nothing landed at the recorded time or now: all of it an hour back
    assert _stored_span_ns(server, "field-c", hi, time.time_ns() + 10**9, wait_s=0) == []


def test_as_needs_a_recording_of_one_vehicle(server: Settings, tmp_path: Path) -> None:
    two = tmp_path / "two.sfrec"
    record(two, vehicles=2, scenario="field_work", duration_s=1.0)
    code, out = _replay(server, two, "--as", "x1")
    assert code == 1
    assert out.strip().splitlines() == [
        f"--as renames one vehicle, but {two} holds 2: sim-0001, sim-0002"
    ]


def test_record_live_writes_what_the_router_delivers(
    server: Settings, drive: Path, tmp_path: Path
) -> None:
    """``record --live`` until Ctrl-C: stopped once a second listener on the router got the
    whole drive (within 120 s), it keeps all of it."""
    out = tmp_path / "live.sfrec"
    endpoint = server.zenoh.listen[0]
    sent = sorted((r.key, r.payload) for r in read_recording(drive))
    heard: list[str] = []
    proc = start_cli(["record", str(out), "--live", "--connect", endpoint, "--duration", "120"])
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("recording fleet/** from")
        keys = {k for k, _ in sent}
        with vehicle_session([endpoint]) as listener:
            # declared, as the recorder's subscriber, before the vehicle connects
            sub = listener.declare_subscriber(
                "fleet/**", lambda s: heard.append(k) if (k := str(s.key_expr)) in keys else None
            )
            with vehicle_session([endpoint]) as vehicle:
                publish_recording(
                    drive, vehicle, rate=4.0, shift_to_now=False, stop=threading.Event()
                )
            poll_until(lambda: len(heard) >= len(sent), "the whole drive heard", timeout_s=120.0)
            sub.undeclare()
        # the recorder is another subscriber of the same router: a moment to take the last too
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    got = sorted((r.key, r.payload) for r in read_recording(out))
    assert got == sent  # byte for byte, alerts and status the server publishes left out
    assert f"wrote {len(sent)} records to {out}" in stdout
    assert {decode(k, p).vehicle_id for k, p in got if "/sensors/" in k} == {"sim-0001"}
