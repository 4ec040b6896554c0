"""MdsfFleet's rules on slip rows (:mod:`estimator.mdsf.fleet`): a slip is valid only when its
std says it is known (``MdsfConfig.valid_slip_std_max_pct``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.config import ConfigError, EncoderConfig, WheeledRearDriveConfig
from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode
from estimator.sim import simulate
from estimator.slip import fit_span_s, unsettled
from estimator.types import EstimateFlag
from estimator.wheel_speed import WheelSpeedConfig
from server.tooling.bench.accuracy import run_estimator

_START_NS = 1_700_000_000_000_000_000
_BOUND_PCT = 2.0
"""A bound the drive's slip std crosses (the default, the tyre's slip range, is crossed less
often on a drive this short)."""
_OFF = 1e9
"""A bound no std reaches: the rule off."""


def _creeping_outage_rows(bound_pct: float, mode: MdsfMode = MdsfMode.PRODUCT) -> np.ndarray:
    """A creeping drive (0.3-0.8 m/s, 30-tooth ring, slip ramps) with a 20 s GNSS outage:
    slow speeds and the outage make the slip's std large in places."""
    cfg = WheeledRearDriveConfig(encoder=EncoderConfig(teeth_per_rev=30))
    sim = simulate(
        "random_drive",
        seed=5,
        start_ns=_START_NS,
        config=cfg,
        duration_s=60.0,
        speed_min_mps=0.3,
        speed_max_mps=0.8,
        gnss_outages=((20.0, 40.0),),
        slip_steps=((15.0, 6.0, 3.0), (30.0, 6.0, 2.0)),
    )
    fleet = MdsfFleet(MdsfConfig(mode=mode, valid_slip_std_max_pct=bound_pct))
    return run_estimator(fleet, sim, dataclasses.replace(sim.config, noise=sim.sensor_noise))


def test_slip_beyond_its_std_bound_is_not_valid() -> None:
    """With the bound, no valid slip has a std above it; the same drive without the bound has
    such rows (the rule is exercised), and the bound changes nothing else: the filter, the
    speeds and every slip within the bound are the same."""
    free = _creeping_outage_rows(_OFF)
    bounded = _creeping_outage_rows(_BOUND_PCT)
    assert np.array_equal(free["stamp_ns"], bounded["stamp_ns"])
    for side, flag in (
        ("left", EstimateFlag.SLIP_LEFT_VALID),
        ("right", EstimateFlag.SLIP_RIGHT_VALID),
    ):
        std_free = free[f"slip_{side}_std_pct"]
        wide = np.isfinite(std_free) & (std_free > _BOUND_PCT)
        assert wide.sum() >= 10, "the drive should give some slips a wide std"
        valid = (bounded["flags"] & int(flag)) != 0
        assert not valid[wide].any()
        assert np.isnan(bounded[f"slip_{side}_pct"][wide]).all()
        assert (bounded[f"slip_{side}_std_pct"][valid] <= _BOUND_PCT).all()
        kept = np.isfinite(std_free) & ~wide
        assert np.array_equal(bounded[f"slip_{side}_pct"][kept], free[f"slip_{side}_pct"][kept])
        assert np.array_equal(valid[kept], ((free["flags"] & int(flag)) != 0)[kept])
    for name in ("vl_mps", "vr_mps", "vg_mps", "rim_left_mps"):
        assert np.array_equal(bounded[name], free[name], equal_nan=True)


def test_paper_mode_keeps_the_source_validity() -> None:
    """Paper mode reproduces the source: its slip is valid above the standstill speed, wide
    std or not, so the bound changes none of its rows."""
    free = _creeping_outage_rows(_OFF, MdsfMode.PAPER)
    bounded = _creeping_outage_rows(_BOUND_PCT, MdsfMode.PAPER)
    std = free["slip_left_std_pct"]
    assert (np.isfinite(std) & (std > _BOUND_PCT)).any()
    for name in free.dtype.names or ():
        assert np.array_equal(bounded[name], free[name], equal_nan=True), name


@pytest.mark.parametrize("bound", [0.0, -1.0, float("nan"), float("inf")])
def test_std_bound_is_checked(bound: float) -> None:
    with pytest.raises(ConfigError, match="valid_slip_std_max_pct"):
        MdsfConfig(valid_slip_std_max_pct=bound)


def _creeping_rows(seed: int) -> tuple[np.ndarray, WheeledRearDriveConfig]:
    """A 60 s creeping drive from rest (0.2-0.8 m/s, 30-tooth ring): fit spans of a second or
    more, speed changes within them."""
    cfg = WheeledRearDriveConfig(encoder=EncoderConfig(teeth_per_rev=30))
    sim = simulate(
        "random_drive",
        seed=seed,
        start_ns=_START_NS,
        config=cfg,
        duration_s=60.0,
        speed_min_mps=0.2,
        speed_max_mps=0.8,
    )
    config = dataclasses.replace(sim.config, noise=sim.sensor_noise)
    return run_estimator(MdsfFleet(), sim, config), config


def _ground_accel(ground_mps: np.ndarray, config: MdsfConfig) -> np.ndarray:
    """The wheel's ground acceleration as the fleet keeps it: the rate of the row's ground
    speed over the tick, low-passed over ``wheel_clock_accel_tau_s`` (rows every tick)."""
    alpha = config.dt_s / (config.wheel_clock_accel_tau_s + config.dt_s)
    out = np.zeros(ground_mps.shape[0])
    for i in range(1, ground_mps.shape[0]):
        rate = (ground_mps[i] - ground_mps[i - 1]) / config.dt_s
        out[i] = out[i - 1] + alpha * (np.nan_to_num(rate) - out[i - 1])
    return out


@pytest.mark.parametrize("seed", [5, 8])
def test_slip_waits_until_the_fit_window_lies_after_a_fast_change(seed: int) -> None:
    """A wheel fit spans ``τ = min_edges·arc/|V|``; a row whose ground speed changed faster than
    the fit follows (``unsettled`` on the wheel's ground acceleration) biases every fit whose
    window holds it, so no slip is valid within ``τ`` after such a row, though the
    acceleration has fallen back by then."""
    rows, config = _creeping_rows(seed)
    stamps_ns = rows["stamp_ns"]
    assert (np.diff(stamps_ns) == MdsfConfig().dt_s * 1e9).all(), "a row every tick"
    t_s = (rows["stamp_ns"] - rows["stamp_ns"][0]) * 1e-9
    geo = config.geometry
    held = 0
    for side, radius_m, flag in (
        ("left", geo.wheel_radius_left_m, EstimateFlag.SLIP_LEFT_VALID),
        ("right", geo.wheel_radius_right_m, EstimateFlag.SLIP_RIGHT_VALID),
    ):
        ground = rows["vl_mps" if side == "left" else "vr_mps"]
        arc_m = radius_m * 2.0 * np.pi / config.encoder.teeth_per_rev
        span_s = fit_span_s(ground, arc_m, WheelSpeedConfig().min_edges)
        accel = _ground_accel(ground, MdsfConfig())
        change_s = t_s[unsettled(ground, accel, span_s, config.slip.settle_max_change)]
        valid = (rows["flags"] & int(flag)) != 0
        assert change_s.size >= 3, "the drive should change speed faster than the fit follows"
        last = np.searchsorted(change_s, t_s, side="right") - 1
        since_s = np.where(last >= 0, t_s - change_s[np.maximum(last, 0)], np.inf)
        assert not (valid & (since_s < span_s)).any()
        held += int(np.count_nonzero(valid & (since_s >= span_s) & (since_s < 2.0 * span_s)))
    assert held > 0, "slip should come back once the window is past the change"
