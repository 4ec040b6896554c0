"""End to end, a tractor beside a steered four-wheel vehicle: both publish over real Zenoh on
loopback → the server (embedded router, pipeline) → a real SQLite store → REST.

``sim-0001`` is a tractor (kind ``wheeled_rear_drive``: MDSF), ``sim-0002`` a steered
four-wheel vehicle (kind ``wheeled_4wd_steered``: friction by default) driving the demo's
loop (:func:`server.tooling.steered_fleet.demo_drive`), which sends IMU, the four CAN wheel
speeds, the steering-wheel angle and GNSS. The friction rows are stored for the second only,
served by series and latest with ``estimator=friction``, μ finite (and within the issue's 10 %
of the road's) wherever flagged informed, held with its σ against the filter elsewhere (none
before the first informed μ), with a position (GeoJSON,
a μ layer on the slip map); the tractor's MDSF rows
cover its drive tick by tick, untouched by the other vehicle's estimator.
"""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pyarrow.parquet as pq
import pytest

from estimator.friction_spec import FrictionFlag
from estimator.geo import EnuFrame
from estimator.mdsf_spec import MDSF_SPEC as MDSF
from estimator.sim import SimRun, simulate
from estimator.sim.four_wheel import simulate_four_wheel
from estimator.types import GnssSample
from server.tooling.fleet_commands import vehicle_session
from server.tooling.fleet_sim import TICK_NS, FleetSim, publish_fleets
from server.tooling.steered_fleet import SteeredFleetSim, demo_drive
from tests.server.fleet_stack import running_server, stack_settings, wait_counted
from tests.server.test_mixed_fleet_end_to_end import _wait_stored
from tests.support import poll_until

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

RATE = 3.0
SEED = 5
SCENARIO = "figure_eight"  # the tractor's: one 27 s lap with start and stop
LAPS = 1
FRICTION_TICK_NS = 20_000_000  # FilterConfig.tick_s


def _publish(endpoints: list[str], prefix: str, t0: int) -> dict[str, int]:
    """Publish the tractor and the steered vehicle on one schedule; packets sent per stream."""
    common: dict[str, Any] = {"prefix": prefix, "seed": SEED, "rate": RATE}
    clock = lambda: t0  # noqa: E731 -- one clock object: fleets on one schedule share it
    with vehicle_session(endpoints) as session:
        fleets = [
            FleetSim(session, 1, scenario=SCENARIO, clock_ns=clock, laps=LAPS, **common),
            SteeredFleetSim(session, 1, first_index=2, clock_ns=clock, **common),
        ]
        assert [f.vehicle_ids for f in fleets] == [["sim-0001"], ["sim-0002"]]
        return dict(publish_fleets(fleets).packets)


def _rows(client: httpx.Client, vid: str, estimator: str, window: dict[str, int]) -> dict:
    """Every stored row of ``estimator`` for ``vid`` (Parquet: exact; null back to NaN)."""
    r = client.get(
        f"/api/v1/vehicles/{vid}/series",
        params={**window, "estimator": estimator, "format": "parquet"},
    )
    assert r.status_code == 200, r.text
    table = pq.read_table(io.BytesIO(r.content))
    return {n: table[n].to_numpy(zero_copy_only=False) for n in table.column_names}


def _check_friction(client: httpx.Client, window: dict[str, int], t0: int) -> None:
    """sim-0002's friction rows: one per 20 ms tick over the drive; μ finite with its σ and
    within 10 % of the road's μ wherever informed; held elsewhere, with a σ at least as large as
    the filter's move away from it (none before the first informed μ); latest = last row."""
    rows = _rows(client, "sim-0002", "friction", window)
    stamps = rows["stamp_ns"]
    drive_s = demo_drive().duration_s
    assert np.unique(np.diff(stamps)).tolist() == [FRICTION_TICK_NS]
    assert stamps[0] - t0 <= 2 * TICK_NS and t0 + drive_s * 1e9 - stamps[-1] <= 2 * TICK_NS
    informed = (rows["flags"] & FrictionFlag.INFORMED) != 0
    assert 0.03 < informed.mean() < 0.5, informed.mean()  # the wet patch's steering step
    mu, mu_std = rows["mu"][informed], rows["mu_std"][informed]
    assert np.isfinite(mu).all() and np.isfinite(mu_std).all() and (mu_std > 0).all()
    road_mu = demo_drive().sample((stamps[informed] - t0) / 1e9)[2]
    assert np.abs(mu / road_mu - 1).max() <= 0.10, np.abs(mu / road_mu - 1).max()
    held = (rows["flags"] & FrictionFlag.HELD) != 0
    assert (held == ~informed).all()
    claimed = held & np.isfinite(rows["mu"])
    assert np.isnan(rows["mu_std"][held & ~claimed]).all()
    moved = np.abs(rows["mu"] - rows["mu_filter"])[claimed]
    assert (rows["mu_std"][claimed] >= moved).all()
    body = client.get(
        "/api/v1/vehicles/sim-0002/series", params={**window, "estimator": "friction"}
    ).json()
    assert body["estimator"] == "friction" and body["stored_rows"] == len(stamps)
    r = client.get("/api/v1/vehicles/sim-0002/latest", params={"estimator": "friction"})
    assert r.status_code == 200, r.text
    latest = r.json()
    assert latest["estimator"] == "friction" and latest["stamp_ns"] == int(stamps[-1])


def _first_fix_frame(t0: int) -> EnuFrame:
    """The ENU frame at sim-0002's first fix (its antenna's, off the CG), as simulated."""
    (run,) = simulate_four_wheel([demo_drive()], seeds=[SEED], start_ns=t0)
    fix = next(m for m in run.measurements if isinstance(m, GnssSample))
    return EnuFrame(fix.lat_deg, fix.lon_deg, fix.height_m)


def _check_position(client: httpx.Client, window: dict[str, int], t0: int) -> None:
    """sim-0002's rows carry its position from GNSS (none dead-reckoned: GNSS all along): its
    track's length is the distance its speed covers (within 2 %), its GeoJSON lies in the
    frame of its first fix (the stored anchor), and its slip map's μ layer holds the informed
    μ of the cells it drove through."""
    rows = _rows(client, "sim-0002", "friction", window)
    east, north = rows["east_m"], rows["north_m"]
    assert np.isfinite(east).all() and np.isfinite(north).all()
    assert np.isfinite(rows["heading_rad"]).all()
    assert not (rows["flags"] & FrictionFlag.DEAD_RECKONED).any()
    track_m = np.hypot(np.diff(east), np.diff(north)).sum()
    speed_m = (rows["vx_mps"][:-1] * np.diff(rows["stamp_ns"]) * 1e-9).sum()
    assert abs(track_m / speed_m - 1) < 0.02, (track_m, speed_m)
    geo = client.get(
        "/api/v1/vehicles/sim-0002/series",
        params={**window, "estimator": "friction", "format": "geojson", "max_points": 100},
    )
    assert geo.status_code == 200, geo.text
    lon, lat, _ = geo.json()["features"][0]["geometry"]["coordinates"]
    first = _first_fix_frame(t0).to_geodetic(east[0], north[0], rows["up_m"][0])
    assert (lat, lon) == pytest.approx((first[0], first[1]), abs=1e-7)  # ~1 cm
    layer = client.get(
        "/api/v1/vehicles/sim-0002/slipmap",
        params={**window, "estimator": "friction", "layer": "mu", "cell_m": 50},
    )
    assert layer.status_code == 200, layer.text
    cells = [c["layer"] for c in layer.json()["cells"] if c["layer"]["samples"]]
    informed = (rows["flags"] & FrictionFlag.INFORMED) != 0
    assert sum(c["samples"] for c in cells) == informed.sum() > 0
    mus = [c["mean"] for c in cells]
    assert min(mus) > 0.3 and max(mus) < 0.9, mus  # the road's 0.35 and 0.8, within 10 %


def _check_tractor(client: httpx.Client, window: dict[str, int], t0: int) -> int:
    """sim-0001's MDSF rows: one per tick from its drive's start to its end, slip where
    flagged valid; no friction rows. Returns its row count."""
    rows = _rows(client, "sim-0001", "mdsf", window)
    run = _tractor_run(t0)
    stamps = rows["stamp_ns"]
    assert np.unique(np.diff(stamps)).tolist() == [TICK_NS]
    assert 0 <= stamps[0] - run.start_ns <= 2 * TICK_NS
    assert 0 <= run.end_ns - stamps[-1] <= 2 * TICK_NS
    for ch in MDSF.slips:  # a slip wherever flagged valid, on both wheels at some time
        valid = (rows["flags"] & MDSF.flag_mask(ch.valid_flag or "")) != 0
        assert valid.any() and np.isfinite(rows[ch.field][valid]).all(), ch.key
    none = client.get(
        "/api/v1/vehicles/sim-0001/series", params={**window, "estimator": "friction"}
    )
    assert none.status_code == 200 and none.json()["stored_rows"] == 0, none.text
    return len(stamps)


def _tractor_run(t0: int) -> SimRun:
    """The tractor's simulated drive (its start and end stamps)."""
    origin: dict[str, Any] = FleetSim.spread_origin(0)
    return simulate(SCENARIO, seed=SEED, start_ns=t0, laps=LAPS, **origin)


def _wait_tails(client: httpx.Client, ends_ns: dict[tuple[str, str], int]) -> None:
    """Until each ``(vehicle, estimator)``'s newest stored row is within two ticks of its
    drive's end: the pipeline releases a vehicle's tail once it falls silent, which a loaded
    host may delay past any fixed quiet spell."""

    def stored() -> bool:
        for (vid, estimator), end_ns in ends_ns.items():
            r = client.get(f"/api/v1/vehicles/{vid}/latest", params={"estimator": estimator})
            if r.status_code != 200 or end_ns - r.json()["stamp_ns"] > 2 * TICK_NS:
                return False
        return True

    poll_until(stored, "rows up to the drives' ends", poll_s=0.3)


def test_tractor_and_steered_vehicle_each_estimated_stored_and_served(tmp_path: Path) -> None:
    settings = stack_settings(tmp_path, None, 0)
    with running_server(settings) as (_, server):
        t0 = time.time_ns()
        sent = _publish(list(settings.zenoh.listen), settings.zenoh.key_prefix, t0)
        assert sent["steering"] == sent["wheel_speeds4"] > 0 and sent["wheels"] > 0
        window = {"start": t0 - 10**9, "end": t0 + 120 * 10**9}
        with httpx.Client(base_url=f"http://127.0.0.1:{server.port}", timeout=30) as client:
            reports = wait_counted(client, 2, sum(sent.values()), window)
            _wait_tails(
                client,
                {
                    ("sim-0001", "mdsf"): _tractor_run(t0).end_ns,
                    ("sim-0002", "friction"): t0 + int(demo_drive().duration_s * 1e9),
                },
            )
            produced = _wait_stored(client)
            vehicles = {v["vehicle_id"]: v for v in client.get("/api/v1/vehicles").json()["data"]}
            assert {vid: v["estimators"] for vid, v in vehicles.items()} == {
                "sim-0001": ["mdsf"],
                "sim-0002": ["friction"],
            }
            for rep in reports.values():
                assert rep["ingest"]["received"] == rep["ingest"]["accepted"], rep["ingest"]
                other = rep["ingest"]["other"]  # counters stored when not zero
                assert other.get("estimator_errors", 0) == other.get("configs_refused", 0) == 0
            _check_friction(client, window, t0)
            _check_position(client, window, t0)
            mdsf_rows = _check_tractor(client, window, t0)
            friction_rows = len(_rows(client, "sim-0002", "friction", window)["stamp_ns"])
            assert mdsf_rows + friction_rows == produced
