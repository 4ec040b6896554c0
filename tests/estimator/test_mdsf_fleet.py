"""MdsfFleet's rules on slip rows (:mod:`estimator.mdsf.fleet`): a slip is valid only when its
std says it is known (``MdsfConfig.valid_slip_std_max_pct``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.config import ConfigError, EncoderConfig, WheeledRearDriveConfig
from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode
from estimator.sim import simulate
from estimator.types import EstimateFlag
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
