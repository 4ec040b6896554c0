"""Random drives: reproducible, independent of how many are drawn, knobs within their ranges."""

from __future__ import annotations

import numpy as np

from estimator.sim import simulate
from estimator.sim.drives import draw_drive, draw_drives


def test_a_drive_depends_on_its_seed_and_index_only() -> None:
    assert draw_drives(10, 5)[3] == draw_drive(5, 3)
    assert draw_drive(5, 3) != draw_drive(6, 3)
    assert draw_drive(5, 3) != draw_drive(5, 4)


def test_knobs_stay_within_the_stated_ranges() -> None:
    drives = draw_drives(300, 11)
    k = [d.knobs() for d in drives]
    creep = np.mean([x["speed_max_mps"] == 0.8 for x in k])
    assert 0.15 < creep < 0.35
    for x in k:
        assert 1.0 <= x["h1_m"] <= 3.5 and 0.8 <= x["h0_m"] <= 1.6
        assert all(abs(e) <= 0.03 for e in x["wheel_radius_error_rel"])
        assert all(abs(c) <= 100.0 for c in x["clock_offset_ms"]) and x["clock_offset_ms"][1] == 0
        assert all(abs(a) <= 3.0 for a in x["imu_misalign_deg"])
        assert x["sway_pitch_deg"] <= 5.0 / max(1.0, x["sway_hz"]) + 1e-9
        assert 0.3 <= x["sway_hz"] <= 3.0
        assert x["teeth_per_rev"] in (20, 30, 48, 60, 90, 120)
        level = 0.0
        for t0, delta, ramp in x["slip_steps"]:
            level += delta
            assert 15.0 <= t0 <= 135.0 and -5.01 <= level <= 20.01 and ramp <= 5.0
        for t0, t1 in x["gnss_outages"]:
            assert t0 >= 10.0 and 10.0 - 0.02 <= t1 - t0 <= 110.0 and t1 <= 140.0
    lengths = [t1 - t0 for x in k for t0, t1 in x["gnss_outages"]]
    assert 0.3 < len(lengths) / len(k) < 0.5 and max(lengths) > 60.0


def test_every_drawn_drive_simulates() -> None:
    for d in draw_drives(4, 12):
        run = simulate(
            "random_drive", seed=d.sim_seed, start_ns=0, config=d.config(), **d.overrides
        )
        assert run.truth["v0_mps"][0] == 0.0
        assert run.config.encoder.teeth_per_rev == d.teeth_per_rev
