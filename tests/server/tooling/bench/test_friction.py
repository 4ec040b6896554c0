"""The friction bench's figures and floors on hand-made series (no simulation)."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np

from server.tooling.bench.friction import Series, _floors, calibration, score

T0_S = 4.0


def _run(name: str = "accelerate_mu08", mu: float = 0.8) -> Any:
    t = np.arange(0.0, 14.0, 0.01)
    manoeuvre = SimpleNamespace(name=name, t0_s=T0_S, mu_step_s=math.nan)
    return SimpleNamespace(
        manoeuvre=manoeuvre, truth=SimpleNamespace(t_s=t, mu=np.full(t.size, mu))
    )


def _series(mu_filter: np.ndarray, informed: np.ndarray) -> Series:
    """Rows every 20 ms; the reported μ is the filter's where informed, else the last informed
    (NaN before the first), as the fleet reports it."""
    t = np.arange(0.0, 14.0, 0.02)[: mu_filter.size]
    reported = np.where(informed, mu_filter, np.nan)
    for k in range(1, reported.size):
        if not informed[k]:
            reported[k] = reported[k - 1]
    return Series(t, mu_filter, reported, informed)


def test_a_start_inside_the_band_is_no_claimed_convergence() -> None:
    """A filter μ that sits 4 % off from the start, never informed: the filter's figure counts
    it converged at once, the claimed one never, and the floor is judged on the claim."""
    n = 700
    s = _series(np.full(n, 0.768), np.zeros(n, dtype=bool))
    sc = score(_run(), s)
    assert sc.conv_s == 0.0
    assert math.isinf(sc.conv_claim_s)
    assert not _floors([_run()], [sc])["accelerate μ 0.8 within 5 % ≤ 1.52 s"]


def test_the_claim_converges_when_an_informed_value_enters_the_band() -> None:
    """Informed from 5.0 s at a μ 2 % off: the claim converges 1.0 s after the start and the
    floor passes; an informed value 8 % off held to the end never converges."""
    n = 700
    t = np.arange(n) * 0.02
    mu = np.where(t < 5.0, 0.6, 0.816)
    sc = score(_run(), _series(mu, t >= 5.0))
    assert abs(sc.conv_claim_s - 1.0) < 1e-9
    assert _floors([_run()], [sc])["accelerate μ 0.8 within 5 % ≤ 1.52 s"]
    off = score(_run(), _series(np.where(t < 5.0, 0.6, 0.864), (t >= 5.0) & (t < 5.5)))
    assert math.isinf(off.conv_claim_s)


def test_calibration_normalises_informed_and_held_rows_by_their_sigma() -> None:
    """Informed from 5.0 to 6.0 s at 0.82 ± 0.01 (truth 0.8: z = 2), then held. Held rows
    that state no σ are judged by the last informed σ (z = 2); rows that state one, by it."""
    n = 700
    t = np.arange(n) * 0.02
    informed = (t >= 5.0) & (t < 6.0)
    s = _series(np.full(n, 0.82), informed)
    std = np.where(informed, 0.01, np.nan)
    cal = calibration(_run(), Series(s.t_s, s.mu_filter, s.mu_reported, informed, std))
    assert cal.z_informed.size == 50
    assert np.allclose(cal.z_informed, 2.0)
    assert cal.z_held.size == int((t >= 6.0).sum())
    assert np.allclose(cal.z_held, 2.0)
    stated = np.where(informed, 0.01, 0.04)
    cal = calibration(_run(), Series(s.t_s, s.mu_filter, s.mu_reported, informed, stated))
    assert np.allclose(cal.z_held, 0.5)
    assert np.all(np.abs(cal.mu_held - 0.8) < 1e-12)
