"""Dead reckoning through GNSS outages: the pure carry, and the fleet estimator's rows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from estimator.config import ConfigError
from estimator.dead_reckoning import DeadReckoning, DeadReckoningConfig
from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode
from estimator.sim import SimRun, replay_arrivals, simulate, truth_at
from estimator.types import EstimateFlag

START_NS = 1_700_000_000_000_000_000
DT_S = 0.1
NAN3 = np.full((1, 3), np.nan)


def _circle(t_s: float, v: float, w: float, psi0: float) -> tuple[float, float, float]:
    """(east, north, heading) at ``t_s`` on a circle from the origin: speed ``v``, yaw rate
    ``w`` (counter-clockwise), heading ``psi0`` at 0 (clockwise from north)."""
    psi = psi0 - w * t_s
    # d/dt (e, n) = v·(sin ψ, cos ψ), ψ = ψ0 − w·t
    e = v / w * (math.cos(psi) - math.cos(psi0))
    n = v / w * (math.sin(psi0) - math.sin(psi))
    return e, n, psi % (2 * math.pi)


def _tick(
    dr: DeadReckoning,
    enu: np.ndarray,
    *,
    heading: float = math.nan,
    v: float = 2.0,
    w: float = 0.0,
    age_s: float = 0.0,
    slot: int = 0,
) -> tuple[np.ndarray, float, bool]:
    out, h, carried = dr.step(
        np.array([slot]),
        enu,
        np.array([age_s]),
        np.array([heading]),
        np.array([v]),
        np.array([w]),
        np.zeros(1),
    )
    return out[0], float(h[0]), bool(carried[0])


def test_carried_positions_follow_a_circle() -> None:
    """A fix, then 20 s without: the carry follows the circle the speed and yaw rate draw
    (the mid-step heading: under 5 mm after 40 m at 0.2 rad/s)."""
    v, w, psi0 = 2.0, 0.2, 0.3
    dr = DeadReckoning(DeadReckoningConfig(), DT_S)
    dr.add(0, (0.0, 0.0))
    pos, head, carried = _tick(dr, np.zeros((1, 3)), heading=psi0, v=v, w=w)
    assert not carried and head == psi0 and (pos == 0).all()
    worst = 0.0
    for k in range(1, 201):
        pos, head, carried = _tick(dr, NAN3, v=v, w=w)
        e, n, psi = _circle(k * DT_S, v, w, psi0)
        assert carried
        assert head == pytest.approx(psi, abs=1e-9)
        worst = max(worst, math.hypot(pos[0] - e, pos[1] - n))
        assert pos[2] == 0.0  # the height is held
    assert worst < 0.005  # 20 s, 40 m of arc


def test_the_antenna_lever_arm_turns_with_the_vehicle() -> None:
    """An antenna 1.5 m ahead and 0.5 m right of ``O``: a fix places the antenna, the carry
    moves ``O`` and puts the antenna back at its arm; turning in place at a standstill moves
    the antenna on a circle of the arm's length about ``O``."""
    dr = DeadReckoning(DeadReckoningConfig(), DT_S)
    dr.add(3, (0.5, 1.5))
    fix = np.array([[10.0, 20.0, 1.0]])
    _tick(dr, fix, heading=0.0, v=1.0, slot=3)  # north: O at (9.5, 18.5)
    w = math.pi / 2 / (10 * DT_S)  # a quarter turn (counter-clockwise) in ten ticks
    for _ in range(10):
        pos, head, carried = _tick(dr, NAN3, v=0.0, w=w, slot=3)
        assert carried
    # facing west: forward is -east, right is +north
    assert head == pytest.approx(1.5 * math.pi)
    assert pos[:2] == pytest.approx([9.5 - 1.5, 18.5 + 0.5], abs=1e-9)


def test_a_stale_fix_is_carried_past_and_a_fresh_one_takes_over() -> None:
    dr = DeadReckoning(DeadReckoningConfig(after_s=0.25), DT_S)
    dr.add(0, (0.0, 0.0))
    _tick(dr, np.zeros((1, 3)), heading=0.0)
    # the fix moved to the tick from 0.2 s ago still places the vehicle; from 0.3 s on, not
    pos, _, carried = _tick(dr, np.array([[0.0, 0.4, 0.0]]), age_s=0.2)
    assert not carried and pos[1] == 0.4
    pos, _, carried = _tick(dr, np.array([[0.0, 9.9, 0.0]]), age_s=0.3)
    assert carried and pos[1] == pytest.approx(0.6)  # 0.4 + 2 m/s · 0.1 s, not 9.9
    pos, _, carried = _tick(dr, np.array([[5.0, 5.0, 0.0]]), heading=math.pi)
    assert not carried and pos[0] == 5.0
    pos, head, carried = _tick(dr, NAN3)
    assert carried and head == math.pi and pos[:2] == pytest.approx([5.0, 4.8])


def test_the_carry_ends_after_max_s_or_without_a_speed() -> None:
    dr = DeadReckoning(DeadReckoningConfig(max_s=1.0), DT_S)
    dr.add(0, (0.0, 0.0))
    dr.add(1, (0.0, 0.0))
    for slot in (0, 1):
        _tick(dr, np.zeros((1, 3)), heading=0.0, slot=slot)
    carried = [_tick(dr, NAN3, slot=0)[2] for _ in range(12)]
    assert carried == [True] * 10 + [False] * 2
    assert np.isnan(_tick(dr, NAN3, slot=0)[0]).all()
    assert not _tick(dr, NAN3, v=math.nan, slot=1)[2]
    assert not _tick(dr, NAN3, slot=1)[2]  # not resumed: the base is gone until a fix
    assert _tick(dr, np.zeros((1, 3)), heading=0.0, slot=1)[2] is False
    assert _tick(dr, NAN3, slot=1)[2]


def test_a_standing_fix_keeps_the_gyro_heading() -> None:
    """At a standstill a course over ground is noise: the heading the gyro carried stays."""
    dr = DeadReckoning(DeadReckoningConfig(min_course_speed_mps=0.5), DT_S)
    dr.add(0, (0.0, 0.0))
    _tick(dr, np.zeros((1, 3)), heading=1.0, v=1.0)
    _tick(dr, np.zeros((1, 3)), heading=2.5, v=0.0)  # standing: course ignored
    _, head, _ = _tick(dr, NAN3, v=1.0)
    assert head == pytest.approx(1.0)


@pytest.mark.parametrize(
    "kw", [{"after_s": -1.0}, {"max_s": math.inf}, {"min_course_speed_mps": math.nan}]
)
def test_config_is_checked(kw: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        DeadReckoningConfig(**kw)


def _rows(sim: SimRun, fleet: MdsfFleet, step_ns: int) -> np.ndarray:
    """``sim`` fed to ``fleet`` as the server's pipeline does, advanced every ``step_ns``."""
    fleet.add_vehicle("v", sim.config)
    parts = []
    for chunk, until in replay_arrivals(
        sim.measurements, sim.arrival_ns, step_ns=step_ns, end_ns=sim.end_ns
    ):
        for m in chunk:
            fleet.push("v", m)
        parts += [rows for _, rows in fleet.advance({"v": until})]
    return np.concatenate(parts)


@pytest.fixture(scope="module")
def outage() -> SimRun:
    return simulate("gnss_outage", seed=1, start_ns=START_NS)


def test_the_track_goes_on_through_a_gnss_outage(outage: SimRun) -> None:
    """The 20 s outage of ``gnss_outage``: every row has a position, those of the outage are
    flagged and within 1 m of the truth (0.52 m measured); the rest is as without the carry."""
    rows = _rows(outage, MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT)), 100_000_000)
    off = _rows(
        outage,
        MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT), dead_reckoning=DeadReckoningConfig(max_s=0)),
        100_000_000,
    )
    carried = (rows["flags"] & int(EstimateFlag.DEAD_RECKONED)) != 0
    assert np.isfinite(rows["east_m"]).all() and np.isfinite(rows["heading_rad"]).all()
    assert 190 <= carried.sum() <= 210
    assert not np.isfinite(off["east_m"][carried]).any()  # no position there without it
    t = (
        truth_at(outage.truth, rows["stamp_ns"], "east_m"),
        truth_at(outage.truth, rows["stamp_ns"], "north_m"),
    )
    err = np.hypot(rows["east_m"] - t[0], rows["north_m"] - t[1])
    assert err[carried].max() < 1.0
    for name in rows.dtype.names or ():
        if name in ("east_m", "north_m", "up_m", "heading_rad", "flags"):
            np.testing.assert_array_equal(rows[name][~carried], off[name][~carried])
        else:
            np.testing.assert_array_equal(rows[name], off[name])


def test_the_carry_is_the_same_in_one_call_as_tick_by_tick(outage: SimRun) -> None:
    """Advanced every 2 s (20 ticks a call, one round per tick) as every 100 ms."""
    fine = _rows(outage, MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT)), 100_000_000)
    coarse = _rows(outage, MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT)), 2_000_000_000)
    n = min(fine.shape[0], coarse.shape[0])
    assert n > 1000
    for name in ("east_m", "north_m", "heading_rad", "flags"):
        np.testing.assert_allclose(coarse[name][:n], fine[name][:n], rtol=0, atol=1e-9)
