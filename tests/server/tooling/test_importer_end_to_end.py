"""``slipfleet import`` end to end: one drive sent over Zenoh to a real server (embedded
router, SQLite), and the same drive as a CSV, a ROS 2 bag and an MCAP file written by the
libraries' own writers, imported with the command into the same store: every estimate row of
an imported vehicle equals the Zenoh vehicle's, field for field (floats to rounding)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import zenoh

from server.app_main import ServerThread, build_app
from server.protocol.codec import encode_gnss, encode_imu, encode_wheel_speeds
from server.protocol.keys import Stream, sensor_key
from server.settings import Settings
from server.storage import open_store
from server.tooling.fleet_commands import vehicle_session
from tests.server.fleet_stack import stack_settings
from tests.server.tooling.import_drive import (
    Drive,
    make_drive,
    write_csv,
    write_mcap,
    write_ros2_bag,
)

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

ZENOH_ID = "over-zenoh"
#: Float fields agree to rounding: the batched engine's sums run over the ticks of each
#: estimator call, and how the pipeline cuts a drive into calls follows the packets' arrival
#: in wall time (a live link's pace, an import's bursts): measured up to 1e-14 m/s apart.
RTOL, ATOL = 1e-9, 1e-9
PRIORITY = {Stream.GNSS: 0, Stream.IMU: 1, Stream.WHEELS: 2}


@dataclass(frozen=True)
class Stored:
    """The store the Zenoh drive went into, and the drive."""

    settings: Settings
    drive: Drive
    window: tuple[int, int]
    config_file: Path


def _wire(drive: Drive, prefix: str) -> list[tuple[str, bytes]]:
    """The drive's packets as its vehicle sends them: the simulator's IMU batches, wheel
    speeds 10 samples a packet, each GNSS epoch alone; in the order their data completes."""
    out: list[tuple[int, int, str, bytes]] = []

    def add(stream: Stream, last_ns: int, payload: bytes) -> None:
        out.append((last_ns, PRIORITY[stream], sensor_key(prefix, ZENOH_ID, stream), payload))

    for k, b in enumerate(drive.imu):
        add(Stream.IMU, int(b.stamp_ns[-1]), encode_imu(b, k))
    w = drive.wheels
    for k, i in enumerate(range(0, len(w.stamp_ns), 10)):
        part = type(w)(w.stamp_ns[i : i + 10], w.omega_radps[i : i + 10])
        add(Stream.WHEELS, int(part.stamp_ns[-1]), encode_wheel_speeds(part, k))
    for k, g in enumerate(drive.gnss):
        add(Stream.GNSS, g.stamp_ns, encode_gnss(g, k))
    out.sort(key=lambda p: (p[0], p[1]))
    return [(key, payload) for _, _, key, payload in out]


def _wait_counted(
    settings: Settings, vehicle_id: str, packets: int, window: dict[str, int]
) -> None:
    import httpx

    deadline = time.monotonic() + 60
    with httpx.Client(base_url=f"http://127.0.0.1:{settings.api.port}", timeout=10) as client:
        while True:
            r = client.get(f"/api/v1/vehicles/{vehicle_id}/report", params=window)
            if r.status_code == 200 and r.json()["ingest"]["received"] >= packets:
                return
            assert time.monotonic() < deadline, f"not {packets} packets counted: {r.text[:300]}"
            time.sleep(0.3)


@pytest.fixture(scope="module")
def stored(tmp_path_factory: pytest.TempPathFactory) -> Stored:
    tmp = tmp_path_factory.mktemp("import")
    settings = stack_settings(tmp, None, 0)
    start_ns = time.time_ns() - 120 * 10**9
    drive = make_drive(start_ns)
    store = open_store(settings.storage)
    store.upsert_vehicle(ZENOH_ID, drive.config.to_dict(), time.time_ns())
    store.close()
    server = ServerThread(build_app(settings), "127.0.0.1", 0)
    server.start()
    try:
        settings.api.port = server.port
        packets = _wire(drive, settings.zenoh.key_prefix)
        with vehicle_session(list(settings.zenoh.listen)) as session:
            pubs: dict[str, zenoh.Publisher] = {}
            for key, payload in packets:
                if key not in pubs:
                    pubs[key] = session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK
                    )
                pubs[key].put(payload)
            window = {"start": start_ns - 10**9, "end": start_ns + 300 * 10**9}
            _wait_counted(settings, ZENOH_ID, len(packets), window)
            for pub in pubs.values():
                pub.undeclare()
    finally:
        server.stop()  # the pipeline flushes its buffers, the writer commits
    config_file = tmp / "vehicle.json"
    config_file.write_text(json.dumps(drive.config.to_dict()))
    return Stored(settings, drive, (start_ns - 10**9, start_ns + 300 * 10**9), config_file)


def _rows(settings: Settings, vehicle_id: str, window: tuple[int, int]) -> np.ndarray:
    store = open_store(settings.storage)
    try:
        return store.query_series(vehicle_id, *window)
    finally:
        store.close()


def _import(stored: Stored, path: Path, vehicle_id: str, monkeypatch: pytest.MonkeyPatch) -> int:
    from server.cli import main

    monkeypatch.setenv("SLIPFLEET_STORAGE__DATA_DIR", str(stored.settings.storage.data_dir))
    return main(
        ["import", str(path), "--vehicle", vehicle_id, "--vehicle-config", str(stored.config_file)]
    )


WRITERS: dict[str, tuple[str, Callable[[Drive, Path], None]]] = {
    "csv": ("drive.csv", write_csv),
    "ros2-bag": ("drive_bag", write_ros2_bag),
    "mcap": ("drive.mcap", write_mcap),
}


@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_imported_drive_has_the_estimates_of_the_same_drive_over_zenoh(
    stored: Stored,
    fmt: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    name, write = WRITERS[fmt]
    path = tmp_path / name
    write(stored.drive, path)
    vehicle_id = f"imported-{fmt}"
    assert _import(stored, path, vehicle_id, monkeypatch) == 0
    out = capsys.readouterr().out
    assert "1239 accepted, 0 duplicate, 0 late, 0 rejected" in out, out

    over_zenoh = _rows(stored.settings, ZENOH_ID, stored.window)
    imported = _rows(stored.settings, vehicle_id, stored.window)
    assert len(over_zenoh) > 300, "the Zenoh drive was estimated"
    assert len(imported) == len(over_zenoh)
    for name in over_zenoh.dtype.names or ():
        if over_zenoh[name].dtype.kind == "f":
            np.testing.assert_allclose(
                imported[name], over_zenoh[name], rtol=RTOL, atol=ATOL, err_msg=name
            )
        else:  # stamps, flags
            np.testing.assert_array_equal(imported[name], over_zenoh[name], err_msg=name)
