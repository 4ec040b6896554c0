"""The batched front end (sensor buffers read per call, every vehicle of a round in one numpy
pass) against the per-vehicle :class:`FrontEnd`, its reference: the same inputs to 1e-9 on
simulated manoeuvres of vehicles of every driven axle, with a soft tyre, tick phases spread,
vehicles joining late, advanced at different intervals and some calls left out; and the
fleet's rows carry them."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.base import Measurement
from estimator.config import DrivenAxle
from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction.fleetfront import FrontEndTicks
from estimator.friction.frontend import FrontEnd
from estimator.friction.sensors import SensedTicks
from estimator.friction_spec import WHEEL_KEYS, FrictionFlag
from estimator.sim.four_wheel import NAMED, FourWheelRun, random_config, simulate_four_wheel
from tests.estimator.friction._reference import TICK_NS, Reference
from tests.estimator.friction.test_fleet import TURN, late_steering, stalled_steering

SECONDS = 9.0
MANOEUVRES = ("steer_mu08", "accelerate_step", "damaged_tyre", "steer_step", "constant_speed")


@pytest.fixture(scope="module")
def runs() -> list[FourWheelRun]:
    """One run per manoeuvre, each on its own random vehicle (driven axles differ)."""
    names = [n for n in MANOEUVRES if n in NAMED]
    assert len(names) >= 4
    configs = [random_config(np.random.default_rng(40 + k)) for k in range(len(names))]
    axles = {c.chassis.driven_axle for c in configs}
    assert len(axles) >= 2, axles
    return simulate_four_wheel([NAMED[n] for n in names], list(range(21, 21 + len(names))), configs)


def _last_ns(m: Measurement) -> int:
    return int(np.atleast_1d(m.stamp_ns)[-1])


def _drive(
    runs: list[FourWheelRun], mode: FrictionMode
) -> tuple[FrictionFleet, dict[str, Reference], dict[str, list[tuple[int, dict[str, object]]]]]:
    """Each run twice (as ``a…`` and ``b…``): ``b`` joins 2.5 s late (its packets from then on)
    and is advanced every 100 ms, ``a`` every 40 ms, ``a2`` only every third call; phases
    spread by ``align_ticks`` on half the vehicles. Returns the fleet, the references, and
    the batched front end's outputs per vehicle ``(t_ns, fields)``."""
    cfg = FrictionFleetConfig(filter=FilterConfig(mode=mode))
    fleet = FrictionFleet(cfg)
    start = runs[0].start_ns
    plan = {}
    for k, r in enumerate(runs):
        plan[f"a{k}"] = (r, start, 40)
        plan[f"b{k}"] = (r, start + 2_500_000_000, 100)
    refs: dict[str, Reference] = {}
    cursor = dict.fromkeys(plan, 0)
    seen: dict[str, list[tuple[int, dict[str, object]]]] = {vid: [] for vid in plan}
    _spy(fleet, seen)
    for step, now in enumerate(range(start, start + round(SECONDS * 1e9), 20_000_000)):
        for n, (vid, (r, join_ns, _)) in enumerate(plan.items()):
            if now < join_ns:
                continue
            if vid not in refs:
                fleet.add_vehicle(vid, r.config)
                aligned = join_ns + n * TICK_NS // len(plan) if n % 2 else None
                if aligned is not None:
                    fleet.align_ticks(vid, aligned)
                refs[vid] = Reference(FrontEnd(r.config, cfg.front, 0.02), aligned)
            ms = r.measurements
            while cursor[vid] < len(ms) and _last_ns(ms[cursor[vid]]) <= now:
                m = ms[cursor[vid]]
                cursor[vid] += 1
                if _last_ns(m) >= join_ns:
                    fleet.push(vid, m)
                    refs[vid].push(m)
        calls = {
            vid: now - 60_000_000
            for vid, (_, _, every_ms) in plan.items()
            if vid in refs and (step * 20) % every_ms == 0 and not (vid == "a2" and step % 3)
        }
        fleet.advance(calls)
        for vid, until in calls.items():
            refs[vid].advance(until)
    return fleet, refs, seen


def _spy(fleet: FrictionFleet, seen: dict[str, list[tuple[int, dict[str, object]]]]) -> None:
    """Record what the fleet's batched front end gives each vehicle (the real step runs)."""
    step = fleet._front.step

    def recording(s: np.ndarray, sensed: SensedTicks) -> FrontEndTicks:
        out = step(s, sensed)
        by_slot = {v.slot: vid for vid, v in fleet._vehicles.items()}
        for i, slot in enumerate(s.tolist()):
            fields = {f: getattr(out, f)[i] for f in FrontEndTicks.__dataclass_fields__}
            seen.setdefault(by_slot[slot], []).append((int(sensed.t_ns[i]), fields))
        return out

    fleet._front.step = recording  # type: ignore[method-assign]


@pytest.mark.parametrize("mode", [FrictionMode.PRODUCT, FrictionMode.PAPER])
def test_batched_front_end_equals_the_per_vehicle_one(
    runs: list[FourWheelRun], mode: FrictionMode
) -> None:
    _, refs, seen = _drive(runs, mode)
    _assert_equal(refs, seen)
    valid = sum(bool(f["valid"]) for got in seen.values() for _, f in got)
    assert valid > 1000  # the comparison covers μ updates, not only the lead-in
    if mode is FrictionMode.PRODUCT:
        assert sum(ref.front.calibrated for ref in refs.values()) >= len(refs) // 2


def test_both_front_ends_agree_through_a_stalled_steering_stream(
    runs: list[FourWheelRun],
) -> None:
    """The same on steered runs (all- and rear-driven: free steered front rims) whose steering
    stream stops for 0.8 s: the stale ticks, their NaN front pair and the restart alike."""
    stalled = [stalled_steering(r)[0] for r in (runs[0], runs[3])]
    assert runs[3].config.chassis.driven_axle is DrivenAxle.REAR
    _, refs, seen = _drive(stalled, FrictionMode.PRODUCT)
    _assert_equal(refs, seen)
    for vid, got in seen.items():
        stale = [f for _, f in got if not f["steering"]]
        assert len(stale) > 20, vid
        assert all(np.isnan(np.asarray(f["kappa"])[:2]).all() for f in stale)
        assert sum(bool(f["valid"]) for _, f in got) > 100, vid


def _assert_equal(
    refs: dict[str, Reference], seen: dict[str, list[tuple[int, dict[str, object]]]]
) -> None:
    """Every vehicle's batched front-end ticks are the per-vehicle reference's (NaN alike)."""
    for vid, ref in refs.items():
        got = seen[vid]
        assert [t for t, _ in got] == list(ref.ticks), vid
        assert len(got) > 150, vid
        for t_ns, fields in got:
            want = ref.ticks[t_ns]
            for name, value in fields.items():
                np.testing.assert_allclose(
                    np.asarray(value, float),
                    np.asarray(getattr(want, name), float),
                    rtol=0,
                    atol=1e-9,
                    err_msg=f"{vid} {name} at {t_ns}",
                )


def test_fleet_rows_carry_the_reference_front_end(runs: list[FourWheelRun]) -> None:
    """The rows' per-wheel load, slip and slip angle, speed, its 1-σ and flags are the reference's
    (through a soft tyre's learnt stiffness), also after a vehicle is removed and its slot
    reused."""
    fleet, refs, _ = _drive(runs[:3], FrictionMode.PRODUCT)
    assert any(ref.front.tyre_suspect for ref in refs.values())
    freed = fleet._vehicles["a0"].slot
    fleet.remove_vehicle("a0")
    fleet.add_vehicle("c", runs[1].config)
    assert fleet._vehicles["c"].slot == freed
    ref = Reference(FrontEnd(runs[1].config, fleet.config.front, 0.02), None)
    rows: list[np.ndarray] = []
    for m in runs[1].measurements:
        if _last_ns(m) > runs[1].start_ns + 5_000_000_000:
            break
        fleet.push("c", m)
        ref.push(m)
        until = _last_ns(m) - 60_000_000
        rows.extend(r for _, r in fleet.advance({"c": until}))
        ref.advance(until)
    got = np.concatenate(rows)
    assert got.size > 200
    assert list(got["stamp_ns"]) == list(ref.ticks)
    for row in got:
        want = ref.ticks[int(row["stamp_ns"])]
        assert abs(row["vx_mps"] - want.vx_mps) < 1e-9
        assert abs(row["vx_std_mps"] - want.vx_std_mps) < 1e-9
        for j, key in enumerate(WHEEL_KEYS):
            assert abs(row[f"fz_{key}_n"] - want.fz_n[j]) < 1e-9
            assert abs(row[f"slip_{key}_pct"] - 100.0 * want.kappa[j]) < 1e-9
            assert abs(row[f"alpha_{key}_rad"] - want.alpha_rad[j]) < 1e-9
        assert bool(row["flags"] & FrictionFlag.GNSS_SPEED) == want.gnss
        assert bool(row["flags"] & FrictionFlag.TYRE_SUSPECT) == want.tyre_suspect


@pytest.fixture(scope="module")
def late_run() -> tuple[FourWheelRun, int]:
    """A 50 km/h turn (steering wheel 90° from ``LEAD_S``) whose steering stream starts late."""
    return late_steering(simulate_four_wheel([TURN], seeds=[11])[0])


def _check_late_steering(ticks: list[tuple[int, dict[str, object]]], first_ns: int) -> None:
    """Before the first steering packet no tick is valid and the front pair's δ, slips, slip
    angles and their 1-σ are NaN, not computed from a straight 0 (the rear pair's known); from
    it on the angle is known and the ticks (moving, calibrated) valid."""
    before = [f for t, f in ticks if t < first_ns]
    after = [f for t, f in ticks if t >= first_ns]
    assert len(before) > 200 and len(after) > 50
    assert not any(bool(f["valid"]) for f in before)
    assert all(np.isnan(np.asarray(f["delta_rad"])[:2]).all() for f in before)
    for name in ("kappa", "alpha_rad", "kappa_std", "alpha_std_rad", "alpha_lag_rad"):
        assert all(np.isnan(np.asarray(f[name])[:2]).all() for f in before), name
        assert all(np.isfinite(np.asarray(f[name])[2:]).all() for f in before), name
        assert all(np.isfinite(np.asarray(f[name])).all() for f in after), name
    assert not any(bool(f["steering"]) for f in before)
    assert all(bool(f["steering"]) and bool(f["valid"]) for f in after)
    assert all(np.isfinite(np.asarray(f["delta_rad"])).all() for f in after)


def test_the_per_vehicle_front_end_waits_for_the_first_steering_angle(
    late_run: tuple[FourWheelRun, int],
) -> None:
    run, first_ns = late_run
    ref = Reference(FrontEnd(run.config, FrictionFleetConfig().front, 0.02), None)
    for m in run.measurements:
        ref.push(m)
    ref.advance(_last_ns(run.measurements[-1]))
    fields = FrontEndTicks.__dataclass_fields__
    ticks = [(t, {f: getattr(tick, f) for f in fields}) for t, tick in ref.ticks.items()]
    _check_late_steering(ticks, first_ns)


def test_the_batched_front_end_waits_for_the_first_steering_angle(
    late_run: tuple[FourWheelRun, int],
) -> None:
    run, first_ns = late_run
    fleet = FrictionFleet()
    fleet.add_vehicle("late", run.config)
    seen: dict[str, list[tuple[int, dict[str, object]]]] = {}
    _spy(fleet, seen)
    for m in run.measurements:
        fleet.push("late", m)
    fleet.advance({"late": _last_ns(run.measurements[-1])})
    _check_late_steering(seen["late"], first_ns)
