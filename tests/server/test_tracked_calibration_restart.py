"""End to end: a crawler's gyro noise measured standing survives a server restart, and so does
an operator's reset.

A simulated crawler (its unit the ADIS16470 its config names) stands, drives and stands again,
publishing over a real Zenoh session on loopback to the server (embedded router, pipeline, the
tracked estimator) and a real SQLite store. Its rows carry the gyro's angle random walk measured
over its stops (``TRACKED_SPEC.calibrations``): converged after one drive. The server is
stopped and started again: the next drive's first row holds the stored measurement (restored,
not measured anew). A reset over REST during that drive makes the estimator forget it: its rows
then hold nothing measured until the drive's last stop measures anew; after another restart the
crawler goes on from that measurement, not the older one. All through the generic calibration
path (spec, registry, ``server.estimation.calibration``, the REST calibration routes).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from estimator.gyro import ADIS16470
from estimator.sim.tracked.route import FIRM, Route, Segment
from estimator.tracked.model import MotionState as M
from server.app_main import ServerThread, build_app
from server.settings import Settings
from server.tooling.fleet_commands import vehicle_session
from server.tooling.tracked_fleet import TrackedFleetSim
from tests.server.fleet_stack import calibration_resets, stack_settings, stored_columns
from tests.support import poll_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

VID = "sim-0001"
S = 1_000_000_000
FIELDS = "gyro_arw_deg_rt_h,gyro_arw_std_deg_rt_h,gnss_clock_offset_s,gnss_clock_offset_std_s"
ROUTE = Route(
    "stand_drive_stand",
    (Segment(M.STOP, 12.0, 0.0), Segment(M.STRAIGHT, 6.0, 3.0), Segment(M.STOP, 12.0, 0.0)),
    FIRM,
    (),
)
DURATION_S = 30.0


def _serve(settings: Settings) -> ServerThread:
    server = ServerThread(build_app(settings), "127.0.0.1", 0)
    server.start()
    return server


def _drive(settings: Settings, start_ns: int, seed: int, rate: float = 4.0) -> int:
    """Publish one run of :data:`ROUTE` from ``start_ns``, ``rate`` times faster than real
    time; its end [ns]."""
    with vehicle_session(list(settings.zenoh.listen)) as session:
        TrackedFleetSim(
            session,
            1,
            routes=[ROUTE],
            prefix=settings.zenoh.key_prefix,
            seed=seed,
            rate=rate,
            clock_ns=lambda: start_ns,
        ).run()
    return start_ns + int(DURATION_S * S)


def _calibration(client: httpx.Client) -> dict:
    r = client.get(f"/api/v1/vehicles/{VID}/calibration", params={"estimator": "tracked"})
    r.raise_for_status()
    [part] = r.json()["estimators"]
    assert part["uncalibrated"] is None  # the tracked spec flags no row for it
    return next(dict(c) for c in part["calibrations"] if c["key"] == "gyro_arw")


def _first_is(rows: dict[str, np.ndarray], newest: tuple[float, float]) -> None:
    got = (rows["gyro_arw_deg_rt_h"][0], rows["gyro_arw_std_deg_rt_h"][0])
    assert got == pytest.approx(newest, rel=1e-9), (got, newest)


def _newest(rows: dict[str, np.ndarray]) -> tuple[float, float]:
    return float(rows["gyro_arw_deg_rt_h"][-1]), float(rows["gyro_arw_std_deg_rt_h"][-1])


def _reset_midway(client: httpx.Client, start_ns: int) -> None:
    """Reset the crawler's calibration once its rows reach the drive's straight (its first
    stop measured), while the drive is being published."""
    deadline = time.monotonic() + 60
    while True:
        r = client.get(
            f"/api/v1/vehicles/{VID}/series",
            params={"start": start_ns, "end": start_ns + 60 * S, "fields": FIELDS},
        )
        if r.status_code == 200 and (r.json()["last_ns"] or 0) >= start_ns + 13 * S:
            break
        assert time.monotonic() < deadline, "the drive's first rows did not arrive"
        time.sleep(0.1)
    assert client.delete(f"/api/v1/vehicles/{VID}/calibration/tracked").status_code == 202


def test_gyro_noise_restored_after_a_restart_and_a_reset_kept(tmp_path: Path) -> None:
    settings = stack_settings(tmp_path, None, 0)
    url = lambda server: f"http://127.0.0.1:{server.port}"  # noqa: E731
    t0 = time.time_ns()

    server = _serve(settings)
    try:
        end_a = _drive(settings, t0, seed=3)
        with httpx.Client(base_url=url(server), timeout=30) as client:
            stored_columns(client, VID, t0, end_a, FIELDS)
            learnt = _calibration(client)
    finally:
        server.stop()
    # measured over two 12 s stops: converged (std below 10 % of itself), near the unit's ARW
    assert learnt["converged"] and learnt["enabled"], learnt
    assert learnt["unit"] == "°/√h" and learnt["limit"] == pytest.approx(0.1 * learnt["value"])
    assert 0.7 < learnt["value"] / ADIS16470.angle_random_walk_deg_rt_h < 1.3, learnt

    server = _serve(settings)
    try:
        with httpx.Client(base_url=url(server), timeout=30) as client:
            rows_a = stored_columns(
                client, VID, t0, end_a, FIELDS
            )  # all stored now, the held rows too
            start_b = end_a + S
            publisher = threading.Thread(target=_drive, args=(settings, start_b, 5, 2.0))
            publisher.start()
            try:
                _reset_midway(client, start_b)
            finally:
                publisher.join()
            end_b = start_b + int(DURATION_S * S)
            rows_b = stored_columns(client, VID, start_b, end_b, FIELDS)
            # restored, not measured anew: the first row holds the newest stored measurement
            _first_is(rows_b, _newest(rows_a))
            # and the receiver's clock goes on from the stored one (standing: a fix barely
            # moves it), not from its 0.15 s prior
            clock = rows_b["gnss_clock_offset_std_s"][0]
            assert clock == pytest.approx(rows_a["gnss_clock_offset_std_s"][-1], rel=1e-2)
            assert clock < 0.1
            # then reset during the straight: nothing measured, and the second stop alone
            arw, std = rows_b["gyro_arw_deg_rt_h"], rows_b["gyro_arw_std_deg_rt_h"]
            reset = np.flatnonzero(np.isnan(arw))
            assert reset.size and np.isfinite(arw[: reset[0]]).all(), arw
            assert np.isfinite(arw[-1]) and std[-1] > 1.2 * std[reset[0] - 1], (std, reset)
            poll_until(lambda: calibration_resets(client, VID) >= 1, "counted reset", timeout_s=10)
    finally:
        server.stop()

    server = _serve(settings)
    try:
        with httpx.Client(base_url=url(server), timeout=30) as client:
            rows_b = stored_columns(client, VID, start_b, end_b, FIELDS)
            start_d = end_b + S
            end_d = _drive(settings, start_d, seed=9)
            rows_d = stored_columns(client, VID, start_d, end_d, FIELDS)
    finally:
        server.stop()
    # the reset survived the restart: the crawler goes on from what it measured after it
    _first_is(rows_d, _newest(rows_b))
