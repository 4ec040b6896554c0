"""The rates at the tick in closed form (the moment matrix's cofactors, ``τ`` powers by products)
against the normal equations solved by ``numpy.linalg`` with ``np.power``: equal on random
windows, and every MDSF row of the advance bench's drives and of random drives equal to 1e-9
with either (the two differ in the last bits of a rate, never in a flag)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode, frontend
from estimator.sim import simulate
from estimator.sim.drives import draw_drive
from server.tooling.bench import SOURCE_START_NS, field_work_sources, push_until
from server.tooling.bench.accuracy import START_NS, run_estimator

Rates = Callable[..., tuple[tuple[np.ndarray, ...], np.ndarray]]


def _rates_by_solve(
    tick_id: np.ndarray,
    tau_s: np.ndarray,
    rates: tuple[np.ndarray, ...],
    means: list[np.ndarray],
    n: np.ndarray,
) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """The quadratic through each tick's window at ``τ = 0``: ``(M⁻¹·r)[0]`` with the inverse
    from LAPACK; the mean where a window has fewer than three samples."""
    m = n.shape[0]
    mom = [np.bincount(tick_id, weights=np.power(tau_s, k), minlength=m) for k in range(5)]
    M = np.array([[mom[i + j] for j in range(3)] for i in range(3)]).transpose(2, 0, 1)
    fit = n >= 3
    M[~fit] = np.eye(3)
    inv = np.linalg.inv(M)
    out = []
    for w, mean in zip(rates, means, strict=True):
        r = np.stack(
            [np.bincount(tick_id, weights=np.power(tau_s, k) * w, minlength=m) for k in range(3)],
            axis=1,
        )
        out.append(np.where(fit, np.einsum("kj,kj->k", inv[:, 0, :], r), mean))
    return tuple(out), np.where(fit, inv[:, 0, 0], 1.0 / np.maximum(n, 1))


@pytest.mark.parametrize("seed", range(5))
def test_rates_at_the_tick_equal_the_solve_on_random_windows(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = rng.integers(0, 13, 200)  # samples per tick, a few with fewer than three
    tick_id = np.repeat(np.arange(n.shape[0]), n)
    # 100 Hz samples jittered by 2 ms, ending at or before the tick
    tau_s = np.concatenate(
        [-np.sort(rng.uniform(0.0, 0.002, k) + 0.01 * np.arange(k))[::-1] for k in n]
    )
    rates: tuple[np.ndarray, ...] = tuple(rng.normal(0.0, sd, tau_s.shape) for sd in (0.5, 0.05))
    means = [
        np.bincount(tick_id, weights=w, minlength=n.shape[0]) / np.maximum(n, 1) for w in rates
    ]
    got, factor = frontend._rates_at_tick(tick_id, tau_s, rates, means, n)
    want, want_factor = _rates_by_solve(tick_id, tau_s, rates, means, n)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(factor, want_factor, rtol=1e-9)


def _bench_rows(seconds: float) -> dict[str, np.ndarray]:
    """Rows of the advance bench's fleet: one vehicle per source run (field_work seeds 1…8),
    tick phases spread, ``advance`` every 50 ms with a 150 ms horizon."""
    sources = field_work_sources(seconds, 8)
    fleet = MdsfFleet()
    ids = [f"v{k}" for k in range(len(sources))]
    for k, vid in enumerate(ids):
        fleet.add_vehicle(vid, sources[k][0])
        fleet.align_ticks(vid, SOURCE_START_NS + k * fleet.config.tick_ns // len(ids))
    streams, pos = [s[1] for s in sources], [0] * len(ids)
    parts: dict[str, list[np.ndarray]] = {vid: [] for vid in ids}
    for s in range(round(seconds * 20)):
        now = SOURCE_START_NS + (s + 1) * 50_000_000
        push_until(fleet, ids, streams, pos, now)
        for vid, rows in fleet.advance(dict.fromkeys(ids, now - 150_000_000)):
            parts[vid].append(rows)
    return {vid: np.concatenate(p) for vid, p in parts.items()}


def _random_rows(index: int) -> dict[str, np.ndarray]:
    """Rows of random drive ``index`` of the draw 1, product mode."""
    d = draw_drive(1, index)
    cfg = d.config()
    sim = simulate("random_drive", seed=d.sim_seed, start_ns=START_NS, config=cfg, **d.overrides)
    return {
        f"random {index}": run_estimator(MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT)), sim, cfg)
    }


def _assert_rows_agree(a: dict[str, np.ndarray], b: dict[str, np.ndarray], tol: float) -> None:
    assert a.keys() == b.keys()
    for vid in a:
        x, y = a[vid], b[vid]
        assert x.dtype == y.dtype and x.shape == y.shape and x.shape[0] > 0, vid
        for name in x.dtype.names or ():
            if x.dtype[name].kind == "f":
                np.testing.assert_allclose(x[name], y[name], rtol=0.0, atol=tol, err_msg=name)
            else:
                np.testing.assert_array_equal(x[name], y[name], err_msg=name)


@pytest.mark.parametrize(
    "rows",
    [lambda: _bench_rows(6.0), lambda: {**_random_rows(0), **_random_rows(3)}],
    ids=["bench_drives", "random_drives"],
)
def test_rows_equal_the_solve_to_1e_9(
    rows: Callable[[], dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    closed_form = rows()
    monkeypatch.setattr(frontend, "_rates_at_tick", _rates_by_solve)
    by_solve = rows()
    _assert_rows_agree(closed_form, by_solve, 1e-9)
