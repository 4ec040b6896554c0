"""The friction fleet: batched equals per-vehicle, rows of its spec, the informed logic, the
source's MEE step both ways, convergence on a model-generated case."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimator._arrays import BoolArray
from estimator.base import FleetEstimator, Measurement
from estimator.config import ConfigError, DrivenAxle, WheeledRearDriveConfig
from estimator.friction import FilterConfig, FrictionFleet, FrictionFleetConfig, FrictionMode
from estimator.friction.brush import brush_forces
from estimator.friction.filter import (
    ProductState,
    TickInputs,
    TyreArrays,
    _gain_mask,
    _input_spread,
    _measure,
    filter_step,
    initial_state,
    mu_of,
    mu_upper,
    reported_mu_std,
)
from estimator.friction.frontend import FrontEndConfig, brake_slip_std, spin_up_slip
from estimator.friction.model import Chassis, body_accelerations
from estimator.friction_spec import FRICTION_SPEC, WHEEL_KEYS, FrictionFlag
from estimator.sim.four_wheel import (
    FOUR_WHEEL_CONFIG,
    INSTANT_WHEEL_SENSOR,
    LEAD_S,
    FourWheelRun,
    Manoeuvre,
    random_config,
    random_manoeuvre,
    simulate_four_wheel,
)
from estimator.sim.four_wheel.dynamics import TruthParams
from estimator.types import SteeringAngles

KMH = 1 / 3.6
TURN = Manoeuvre(
    "turn",
    LEAD_S + 3.0,
    ((0.0, 50 * KMH), (1e4, 50 * KMH)),
    ((0.0, 0.0), (LEAD_S, 0.0), (LEAD_S + 0.3, math.radians(90)), (1e4, math.radians(90))),
    ((0.0, 0.4), (1e4, 0.4)),
)
STRAIGHT = Manoeuvre(
    "straight",
    LEAD_S + 3.0,
    ((0.0, 40 * KMH), (1e4, 40 * KMH)),
    ((0.0, 0.0), (1e4, 0.0)),
    ((0.0, 0.8), (1e4, 0.8)),
)


LATE_STEERING_S = 1.0
"""How far into the turn the late vehicle's first steering packet comes [s]."""


def late_steering(run: FourWheelRun) -> tuple[FourWheelRun, int]:
    """``run`` with its steering packets dropped until ``LATE_STEERING_S`` into its turn (IMU,
    wheels and GNSS from the start), and the first kept steering stamp."""
    cut = run.start_ns + round((LEAD_S + LATE_STEERING_S) * 1e9)
    kept = [
        m
        for m in run.measurements
        if not (isinstance(m, SteeringAngles) and int(np.atleast_1d(m.stamp_ns)[0]) < cut)
    ]
    first = min(int(m.stamp_ns[0]) for m in kept if isinstance(m, SteeringAngles))
    return dataclasses.replace(run, measurements=kept), first


STALL_S = (1.4, 2.2)
"""When, from the turn's start, the stalled vehicle's steering stream stops and resumes [s]."""


def stalled_steering(run: FourWheelRun) -> tuple[FourWheelRun, int, int]:
    """``run`` with its steering packets stamped in ``STALL_S`` of its turn dropped (IMU,
    wheels and GNSS throughout), the last angle's stamp before the gap and the first after."""
    lo, hi = (run.start_ns + round((LEAD_S + t) * 1e9) for t in STALL_S)
    kept = []
    for m in run.measurements:
        first = int(np.atleast_1d(m.stamp_ns)[0])
        if not (isinstance(m, SteeringAngles) and lo <= first < hi):
            kept.append(m)
    angles = np.concatenate([m.stamp_ns for m in kept if isinstance(m, SteeringAngles)])
    return (
        dataclasses.replace(run, measurements=kept),
        int(angles[angles < lo].max()),
        int(angles[angles >= hi].min()),
    )


_STEERED_COLUMNS = (("slip", "pct"), ("alpha", "rad"), ("util", "pct"))
"""The per-wheel columns computed with the wheel's steer angle (name, unit)."""


def front_columns_empty(rows: np.ndarray) -> BoolArray:
    """Per row: the front pair's slip, slip-angle and grip-used columns all NaN."""
    front = [f"{c}_{k}_{u}" for k in WHEEL_KEYS[:2] for c, u in _STEERED_COLUMNS]
    return np.all([np.isnan(rows[c]) for c in front], axis=0)


def rear_columns_known(rows: np.ndarray) -> BoolArray:
    """Per row: the rear pair's slip, slip-angle and grip-used columns all finite."""
    rear = [f"{c}_{k}_{u}" for k in WHEEL_KEYS[2:] for c, u in _STEERED_COLUMNS]
    return np.all([np.isfinite(rows[c]) for c in rear], axis=0)


@pytest.fixture(scope="module")
def runs() -> list[FourWheelRun]:
    return simulate_four_wheel([TURN, STRAIGHT], seeds=[11, 12])


def _drive(fleet: FrictionFleet, runs: list[FourWheelRun], ids: list[str]) -> dict[str, np.ndarray]:
    """Feed each run's packets 100 ms at a time and advance the fleet's vehicles together."""
    out: dict[str, list[np.ndarray]] = {i: [] for i in ids}
    cursor = dict.fromkeys(ids, 0)
    start = runs[0].start_ns
    for now in range(start, start + 8_000_000_000, 100_000_000):
        for vid, r in zip(ids, runs, strict=True):
            ms = r.measurements
            while cursor[vid] < len(ms) and _last(ms[cursor[vid]]) <= now:
                fleet.push(vid, ms[cursor[vid]])
                cursor[vid] += 1
        for vid, rows in fleet.advance(dict.fromkeys(ids, now)):
            assert rows.dtype is FRICTION_SPEC.dtype
            out[vid].append(rows)
    return {k: np.concatenate(v) for k, v in out.items()}


def _last(m: Measurement) -> int:
    st = m.stamp_ns
    return int(st[-1]) if hasattr(st, "__len__") else int(st)


@pytest.mark.parametrize("mode", [FrictionMode.PRODUCT, FrictionMode.PAPER])
def test_batched_equals_per_vehicle(runs: list[FourWheelRun], mode: FrictionMode) -> None:
    cfg = FrictionFleetConfig(filter=FilterConfig(mode=mode))
    both = FrictionFleet(cfg)
    for vid, r in zip(("a", "b"), runs, strict=True):
        both.add_vehicle(vid, r.config)
    batched = _drive(both, runs, ["a", "b"])
    for vid, r in zip(("a", "b"), runs, strict=True):
        alone = FrictionFleet(cfg)
        alone.add_vehicle(vid, r.config)
        single = _drive(alone, [r], [vid])[vid]
        got = batched[vid]
        assert got.shape == single.shape and got.size > 300
        for name in FRICTION_SPEC.field_names:
            a, b = got[name].astype(float), single[name].astype(float)
            assert np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True), name


def test_informed_logic_holds_the_last_informed_mu(runs: list[FourWheelRun]) -> None:
    fleet = FrictionFleet()
    assert isinstance(fleet, FleetEstimator)
    for vid, r in zip(("turn", "straight"), runs, strict=True):
        fleet.add_vehicle(vid, r.config)
    rows = _drive(fleet, runs, ["turn", "straight"])
    for vid in ("turn", "straight"):
        got = rows[vid]
        informed = (got["flags"] & FrictionFlag.INFORMED) > 0
        held = (got["flags"] & FrictionFlag.HELD) > 0
        assert np.all(informed ^ held)
        assert np.all(np.isfinite(got["mu_std"][informed]))
        assert np.all(got["mu_std"][informed] / got["mu"][informed] < 0.04)
        # a held μ states its 1-σ against the filter now: at least how far the filter has
        # moved from it; none before the first informed μ
        claimed = held & np.isfinite(got["mu"])
        assert np.all(np.isnan(got["mu_std"][held & ~claimed]))
        assert np.all(np.isfinite(got["mu_std"][claimed]))
        moved = np.abs(got["mu"] - got["mu_filter"])[claimed]
        assert np.all(got["mu_std"][claimed] >= moved)
        last = math.nan
        for mu, inf in zip(got["mu"], informed, strict=True):  # a held row repeats the last
            if not inf:
                assert (math.isnan(mu) and math.isnan(last)) or mu == last
            last = mu
    # straight constant speed: the tyres use little grip; μ is not informed
    straight = rows["straight"]
    assert np.mean((straight["flags"] & FrictionFlag.INFORMED) > 0) < 0.05


def test_reported_mu_std_by_hand() -> None:
    """Informed (the reported μ is the filter's): the filter's σ. Held at 0.50 while the
    filter reads 0.38 ± 0.05: √(0.05² + 0.12²) = 0.13. Nothing reported yet: NaN."""
    got = reported_mu_std(
        np.array([0.62, 0.50, math.nan]), np.array([0.62, 0.38, 0.6]), np.array([0.01, 0.05, 0.2])
    )
    assert got[0] == pytest.approx(0.01, abs=1e-15)
    assert got[1] == pytest.approx(0.13, abs=1e-12)
    assert math.isnan(got[2])


def test_a_held_mu_states_its_sigma_against_the_filter() -> None:
    """A turn on μ 0.4 claims μ, then straight ahead nothing informs it: the held rows after
    the claim state a finite 1-σ, at least the filter's move away from the held value."""
    turn_then_straight = Manoeuvre(
        "turn_then_straight",
        LEAD_S + 5.0,
        ((0.0, 50 * KMH), (1e4, 50 * KMH)),
        (
            (0.0, 0.0),
            (LEAD_S, 0.0),
            (LEAD_S + 0.3, math.radians(90)),
            (LEAD_S + 2.5, math.radians(90)),
            (LEAD_S + 2.8, 0.0),
            (1e4, 0.0),
        ),
        ((0.0, 0.4), (1e4, 0.4)),
    )
    run = simulate_four_wheel([turn_then_straight], seeds=[11])[0]
    fleet = FrictionFleet()
    fleet.add_vehicle("v", run.config)
    rows = _drive(fleet, [run], ["v"])["v"]
    informed = (rows["flags"] & FrictionFlag.INFORMED) > 0
    after = np.arange(informed.size) > np.flatnonzero(informed)[0]
    held = after & ~informed
    assert held.sum() > 50
    assert np.all(np.isfinite(rows["mu_std"][held]))
    moved = np.abs(rows["mu"] - rows["mu_filter"])[held]
    assert np.all(rows["mu_std"][held] >= moved)
    assert np.all(rows["mu_std"][held] > 0)


def test_refuses_other_kinds() -> None:
    with pytest.raises(ConfigError, match="wheeled_4wd_steered"):
        FrictionFleet().add_vehicle("t", WheeledRearDriveConfig())


def _slip_angles(chassis: Chassis, vx: float, vy: float, r: float, delta: np.ndarray) -> np.ndarray:
    """Each wheel's slip angle ``(1, 4)`` of a body moving at ``(vx, vy)`` m/s turning at ``r``
    rad/s, its wheels steered by ``delta``: the wheel's velocity in its own frame,
    ``α = −atan2(v_lat, v_long)``."""
    along = vx - chassis.wheel_y_m * r
    across = vy + chassis.wheel_x_m * r
    v_long = along * np.cos(delta) + across * np.sin(delta)
    v_lat = -along * np.sin(delta) + across * np.cos(delta)
    return np.asarray(-np.arctan2(v_lat, v_long))


def _model_inputs(mu: float, n: int, seed: int) -> tuple[list[TickInputs], Chassis, TyreArrays]:
    """Ticks whose measurements the filter's own model makes from random heavy slips: a rigid
    body at 15 m/s turning at a random yaw rate, its lateral speed following
    ``v̇_y = a_y − r v_x`` from the forces, gives each wheel its slip angle."""
    rng = np.random.default_rng(seed)
    cfg = FOUR_WHEEL_CONFIG
    chassis = Chassis.of([cfg])
    t = cfg.tyre
    tyres = TyreArrays(
        *(np.array([[v]]) for v in (t.kz_npm, t.unloaded_radius_m, t.c_px_npm2, t.c_py_npm2))
    )
    ticks = []
    vy = 0.0
    for _ in range(n):
        fz = np.full((1, 4), 6000.0) + rng.normal(0, 300, (1, 4))
        kappa = rng.uniform(0.0, 0.03, (1, 4))
        vx, r = 15.0, 0.25 + rng.uniform(-0.05, 0.05)
        delta = np.array([[0.05, 0.05, 0.0, 0.0]])
        alpha = _slip_angles(chassis, vx, vy, r, delta)
        cx, cy = tyres.stiffness(fz)
        fx, fy = brush_forces(kappa, alpha, fz, mu, cx, cy)
        z = body_accelerations(fx[:, None], fy[:, None], delta[:, None], chassis)[:, 0]
        tiny = np.full((1, 4), 1e-5)
        vy_now = vy
        vy += (float(z[0, 1]) - r * vx) * 0.02
        ticks.append(
            TickInputs(
                fz_n=fz,
                alpha_rad=alpha,
                delta_rad=delta,
                kappa=kappa,
                kappa_std=tiny,
                kappa_common_std=np.zeros(1),
                alpha_std_rad=tiny,
                z=z,
                valid=np.array([True]),
                vx_mps=np.array([vx]),
                yaw_rate_radps=np.array([r]),
                vy_meas_mps=np.array([vy_now]),
                vy_meas_std_mps=np.array([0.05]),
                alpha_lag_rad=np.zeros((1, 4)),
                radius_m=np.full((1, 4), t.unloaded_radius_m),
                balance_std_n=np.full((1, 2), 1e6),  # random slips: no differential
            )
        )
    return ticks, chassis, tyres


@pytest.mark.parametrize("mode", list(FrictionMode))
def test_every_filter_finds_mu_from_its_own_model(mode: FrictionMode) -> None:
    ticks, chassis, tyres = _model_inputs(0.45, 150, seed=3)
    cfg = FilterConfig(mode=mode)
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    for u in ticks:
        st = filter_step(st, cfg, tyres, chassis, u)
    assert mu_of(st.x[0, 0], mode) == pytest.approx(0.45, rel=0.02)
    p = st.s[0] @ st.s[0].T
    assert np.all(np.linalg.eigvalsh(p) > 0)


def test_paper_mode_mee_both_ways() -> None:
    """Consistent measurements: the MEE covariance is positive definite and used; an absurd
    one leaves an entry without kernel weight: the standard SCKF step runs instead."""
    ticks, chassis, tyres = _model_inputs(0.6, 2, seed=4)
    cfg = FilterConfig(mode=FrictionMode.PAPER, mee_kernel_sigma=1.0)
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    good = filter_step(st, cfg, tyres, chassis, ticks[0])
    assert good.mee_ok[0] and good.updated[0]
    u = ticks[1]
    wild = dataclasses.replace(u, z=u.z + np.array([[400.0, -900.0, 2500.0]]))
    bad = filter_step(good, cfg, tyres, chassis, wild)
    assert bad.updated[0] and not bad.mee_ok[0]


def test_a_soft_tyre_has_its_vertical_stiffness_learnt() -> None:
    """kz 50,000 N/m on the rear left (config: the nominal 250,000): its rolling radius sinks
    five times as far, the rows say TYRE_SUSPECT, the front end learns ρ from the other three
    (within 0.03 of the truth's) and that tyre's kz (within 10 %), the others keep the
    config's; μ flagged informed is within 10 % of the truth's."""
    soft = dataclasses.replace(TURN, name="soft_turn", damaged_wheel=2)
    run = simulate_four_wheel([soft], seeds=[13])[0]
    kz = np.full((1, 4), run.config.tyre.kz_npm)
    kz[0, 2] = soft.damaged_kz_npm
    truth = TruthParams.draw([run.config], [np.random.default_rng(13)], kz)
    fleet = FrictionFleet()
    fleet.add_vehicle("soft", run.config)
    rows = _drive(fleet, [run], ["soft"])["soft"]
    late = rows["stamp_ns"] > run.start_ns + 3_000_000_000  # radius calibrated by then
    assert np.all((rows["flags"][late] & FrictionFlag.TYRE_SUSPECT) > 0)
    slot = fleet._vehicles["soft"].slot
    assert abs(fleet._front.radius_drop(slot) - float(truth.radius_drop[0])) < 0.03
    kz = fleet._front.kz_wheel(slot)
    assert abs(kz[2] / soft.damaged_kz_npm - 1.0) < 0.1
    assert np.all(kz[[0, 1, 3]] == run.config.tyre.kz_npm)
    informed = (rows["flags"] & FrictionFlag.INFORMED) > 0
    assert np.all(np.abs(rows["mu"][informed] / 0.4 - 1.0) < 0.1)


def test_gain_mask_learns_each_state_where_it_is_told_apart() -> None:
    """Straight ahead at small slip: μ and the lateral factors are held, the rear (driving)
    factor learns; deep in a turn at 0.4 of the grip: μ learns, the factors are held."""
    ticks, _, tyres = _model_inputs(0.4, 1, seed=6)
    cfg = FilterConfig()
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    quiet = dataclasses.replace(
        ticks[0],
        kappa=np.array([[0.0, 0.0, 0.003, 0.003]]),
        kappa_std=np.full((1, 4), 2e-4),
        alpha_rad=np.zeros((1, 4)),
        alpha_std_rad=np.full((1, 4), 1e-3),
    )
    held = _gain_mask(st.x, st.s, cfg, tyres, quiet)[0]
    assert held[ProductState.GX_REAR] == 1 and held[ProductState.GX_FRONT] == 0
    assert held[ProductState.LN_MU] == 0 and held[ProductState.VY] == 1
    assert held[ProductState.GY_FRONT] == 0 and held[ProductState.GY_REAR] == 0
    turning = dataclasses.replace(ticks[0], alpha_rad=np.full((1, 4), 0.05))
    learns = _gain_mask(st.x, st.s, cfg, tyres, turning)[0]
    assert learns[ProductState.LN_MU] == 1
    assert learns[ProductState.GY_FRONT] == 0 and learns[ProductState.GY_REAR] == 0


def test_the_speed_error_moves_the_four_slips_together() -> None:
    """``D``'s last column (the shared κ error, one speed error over all four wheels) is the
    per-wheel columns' sum scaled to its 1-σ (the model is near linear at small slip), and it
    adds no spread where it is zero."""
    ticks, chassis, tyres = _model_inputs(0.6, 1, seed=3)
    cfg = FilterConfig()
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    own = np.full((1, 4), 1e-6)
    u = dataclasses.replace(ticks[0], kappa_std=own, kappa_common_std=np.array([2e-6]))
    d = _input_spread(st.x, cfg, tyres, chassis, u)
    assert d.shape == (1, 6, 6)  # a_x, a_y, ṙ, v_y and the two axles' torque balances
    np.testing.assert_allclose(d[..., 4], 2.0 * d[..., :4].sum(axis=-1), rtol=1e-3, atol=1e-12)
    assert np.abs(d[0, 0, 4]) > 0
    quiet = dataclasses.replace(u, kappa_common_std=np.zeros(1))
    assert np.all(_input_spread(st.x, cfg, tyres, chassis, quiet)[..., 4] == 0)


def test_the_relaxation_length_spreads_a_lagging_slip_angle() -> None:
    """``D``'s sixth column is the change of ``h`` when the four wheels' α lag grows by
    ``relaxation_rel_std`` (the tyres' relaxation length is the config's ×0.75-1.75), zero
    without a lag; a tick whose ``a_y`` is what the 1.5× longer lag gives (a tyre relaxing
    more slowly than the config says, in a steering ramp) moves ``v_y`` less than with the
    lag taken as exact."""
    ticks, chassis, tyres = _model_inputs(0.6, 1, seed=3)
    cfg = FilterConfig()
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    u = dataclasses.replace(ticks[0], alpha_lag_rad=np.full((1, 4), -3e-3))
    longer = dataclasses.replace(u, alpha_lag_rad=u.alpha_lag_rad * 1.5)
    mean, kappa, alpha = st.x[:, None, :], u.kappa[:, None, :], u.alpha_rad[:, None, :]
    z_longer = _measure(mean, cfg, tyres, chassis, longer, kappa, alpha)[:, 0]
    expect = z_longer - _measure(mean, cfg, tyres, chassis, u, kappa, alpha)[:, 0]
    d = _input_spread(st.x, cfg, tyres, chassis, u)
    np.testing.assert_allclose(d[..., 5], expect, rtol=1e-12, atol=1e-12)
    assert abs(d[0, 1, 5]) > 0.1  # m/s²: 1.5e-3 rad on four tyres of ~80 kN/rad, 2,500 kg
    still = dataclasses.replace(u, alpha_lag_rad=np.zeros((1, 4)))
    assert np.all(_input_spread(st.x, cfg, tyres, chassis, still)[..., 5] == 0)
    z = u.z.copy()
    z[:, :3] = z_longer[:, :3]
    slower = dataclasses.replace(u, z=z)
    moved = []
    for rel in (0.0, 0.5):
        c = FilterConfig(relaxation_rel_std=rel)
        out = filter_step(initial_state(c, tyres, u.fz_n), c, tyres, chassis, slower)
        moved.append(abs(out.x[0, ProductState.VY] - st.x[0, ProductState.VY]))
    assert moved[1] < 0.9 * moved[0]


def test_spin_up_slip_by_hand() -> None:
    """``κ = −I a_x/(r² c_x)``: 1.5 kg·m², 2 m/s², r 0.32 m, c_x 300,000 N → −9.765625e-5;
    braking turns its sign; per wheel ``(B, 4)`` with ``(B, 1)`` accelerations."""
    radius, c_x = np.full(4, 0.32), np.full(4, 3e5)
    assert np.allclose(spin_up_slip(2.0, radius, c_x, 1.5), -9.765625e-5, rtol=1e-12)
    assert np.allclose(spin_up_slip(-2.0, radius, c_x, 1.5), 9.765625e-5, rtol=1e-12)
    both = spin_up_slip(np.array([[2.0], [0.0]]), np.tile(radius, (2, 1)), c_x, 1.5)
    assert both.shape == (2, 4) and np.all(both[1] == 0.0)


def test_the_undriven_wheels_spin_up_slip_leaves_the_speed() -> None:
    """Accelerating 40 → 70 km/h in 4 s (2.1 m/s²) on a rear-driven vehicle: its free-rolling
    front wheels are spun up by their contact force and roll with κ ≈ −1e-4 (the truth's,
    wheel inertia 0.8-2 kg·m²). Taken out of their rim speed, the front end's front κ
    follows the truth's within 3e-5 (mean over the acceleration); read as free rolling
    (``wheel_inertia_kgm2`` 0), they read ~0 and every κ is ~1e-4 high."""
    ramp = Manoeuvre(
        "ramp",
        LEAD_S + 4.0,
        ((0.0, 40 * KMH), (LEAD_S, 40 * KMH), (LEAD_S + 4.0, 70 * KMH)),
        ((0.0, 0.0), (1e4, 0.0)),
        ((0.0, 0.6), (1e4, 0.6)),
    )
    run = simulate_four_wheel([ramp], seeds=[31])[0]
    errors = []
    for inertia in (FrontEndConfig().wheel_inertia_kgm2, 0.0):
        fleet = FrictionFleet(
            FrictionFleetConfig(frontend=FrontEndConfig(wheel_inertia_kgm2=inertia))
        )
        fleet.add_vehicle("ramp", run.config)
        rows = _drive(fleet, [run], ["ramp"])["ramp"]
        t_s = (rows["stamp_ns"] - run.start_ns) / 1e9
        during = (t_s > LEAD_S + 0.5) & (t_s < LEAD_S + 3.9)
        front = (rows["slip_fl_pct"] + rows["slip_fr_pct"]) / 200
        truth = np.interp(t_s, run.truth.t_s, run.truth.kappa[:, :2].mean(axis=1))
        assert float(truth[during].mean()) < -5e-5
        errors.append(float((front - truth)[during].mean()))
    assert abs(errors[0]) < 3e-5
    assert errors[1] > 6e-5


def test_brake_slip_std_by_hand() -> None:
    """``κ = s m a/(2 c_x)`` per unit share: 2,000 kg braked by 1.5 m/s², c_x 200,000 N →
    7.5e-3; nothing while the tyres drive; per wheel ``(B, 4)`` with ``(B, 1)`` decelerations."""
    c_x = np.full(4, 2e5)
    assert np.allclose(brake_slip_std(1.5, 2000.0, c_x), 7.5e-3, rtol=1e-12)
    assert np.all(brake_slip_std(-1.5, 2000.0, c_x) == 0.0)
    both = brake_slip_std(np.array([[1.5], [0.0]]), np.array([[2000.0], [2000.0]]), c_x)
    assert both.shape == (2, 4) and np.all(both[1] == 0.0)


BRAKE = Manoeuvre(
    "brake",
    LEAD_S + 4.0,
    ((0.0, 60 * KMH), (LEAD_S, 60 * KMH), (LEAD_S + 4.0, 38 * KMH)),
    ((0.0, 0.0), (1e4, 0.0)),
    ((0.0, 0.45), (1e4, 0.45)),
)


@pytest.mark.parametrize("axle", [DrivenAxle.FRONT, DrivenAxle.REAR])
def test_braked_undriven_rims_do_not_read_the_speed(axle: DrivenAxle) -> None:
    """Braking 60 → 38 km/h in 4 s (1.5 m/s²): the service brakes act on every wheel, so the
    undriven ("free") wheels slip by ~3e-3 (their axle's share of the braking). Read as free
    rolling (``brake_share_std`` 0, as before) they pull the speed down by that much and
    every κ with it: the four read ~3e-3 above the truth's, braked slips read as none. Left
    out while braking, the speed leans on GNSS and the accelerometer, and the slips' shared
    error stays within 1e-3 (measured 1-3e-4 on either drive). On instantaneous wheel speeds:
    an ECU's mean over its 20 ms period lags by 10 ms, which the front end does not take, and
    adds ``a·T/2/v`` ≈ 1.1e-3 to that error here (measured 1.43e-3, 1.27e-3)."""
    config = dataclasses.replace(
        FOUR_WHEEL_CONFIG,
        chassis=dataclasses.replace(FOUR_WHEEL_CONFIG.chassis, driven_axle=axle),
    )
    run = simulate_four_wheel(
        [BRAKE], seeds=[41], configs=[config], wheel_sensors=[INSTANT_WHEEL_SENSOR]
    )[0]
    shared = []
    for share in (FrontEndConfig().brake_share_std, 0.0):
        fleet = FrictionFleet(FrictionFleetConfig(frontend=FrontEndConfig(brake_share_std=share)))
        fleet.add_vehicle("brake", run.config)
        rows = _drive(fleet, [run], ["brake"])["brake"]
        t_s = (rows["stamp_ns"] - run.start_ns) / 1e9
        during = (t_s > LEAD_S + 1.0) & (t_s < LEAD_S + 3.9)
        slips = np.stack([rows[f"slip_{w}_pct"] for w in ("fl", "fr", "rl", "rr")], 1) / 100
        truth = np.stack(
            [np.interp(t_s, run.truth.t_s, run.truth.kappa[:, j]) for j in range(4)], 1
        )
        assert float(truth[during].mean()) < -1.5e-3
        shared.append(float((slips - truth)[during].mean()))
    assert abs(shared[0]) < 1e-3
    assert shared[1] > 1.5e-3


def test_mu_learns_only_where_the_speeds_error_leaves_the_grip_known() -> None:
    """Braking at a third of the grip with κ −4e-3 on every wheel: with the speed known to
    1e-4 (the rims read it) ``ln μ`` learns; with it known to 1.5e-3 only (the rims braked,
    GNSS and the accelerometer alone), that error is a third of the slips in use, correlated
    over seconds, and ``ln μ`` is held."""
    ticks, _, tyres = _model_inputs(0.4, 1, seed=6)
    cfg = FilterConfig()
    st = initial_state(cfg, tyres, ticks[0].fz_n)
    st.x[0, ProductState.LN_MU] = math.log(0.4)
    st.s[0, ProductState.LN_MU, ProductState.LN_MU] = 0.05  # μ learnt to 5 %
    braking = dataclasses.replace(
        ticks[0],
        kappa=np.full((1, 4), -4e-3),
        kappa_std=np.full((1, 4), 5e-4),
        alpha_rad=np.zeros((1, 4)),
        z=np.array([[-2.5, 0.0, 0.0]]),
    )
    known = dataclasses.replace(braking, kappa_common_std=np.array([1e-4]))
    drifting = dataclasses.replace(braking, kappa_common_std=np.array([1.5e-3]))
    assert _gain_mask(st.x, st.s, cfg, tyres, known)[0, ProductState.LN_MU] == 1
    assert _gain_mask(st.x, st.s, cfg, tyres, drifting)[0, ProductState.LN_MU] == 0


def test_braking_before_a_turn_leaves_mu_right_accelerating_in_it() -> None:
    """The bench's random drive 40,101 (hold-out set 301, 302), its first 14 s: a front-driven
    2,160 kg vehicle on μ 0.43 brakes for 4 s, turns at 85 % of the grip, then accelerates
    in the turn with its front wheels at κ 0.05-0.07. The braked rear rims had read the
    speed 3e-3 low, the front axle's ``g_x`` learnt 2.2 from it, and μ in the turn was
    10-15 % low and flagged informed. Now, accelerating in the turn (12-14 s), the filter's
    μ stays within 6 % of the truth and no row is flagged informed beyond 10 %."""
    rng = np.random.default_rng(40_101)
    drive = dataclasses.replace(random_manoeuvre(rng, 1), duration_s=14.0)
    run = simulate_four_wheel([drive], seeds=[40_101], configs=[random_config(rng)])[0]
    assert run.config.chassis.driven_axle is DrivenAxle.FRONT
    fleet = FrictionFleet()
    fleet.add_vehicle("v", run.config)
    cursor, parts = 0, []
    for now in range(run.start_ns, run.start_ns + 14_000_000_000, 100_000_000):
        while cursor < len(run.measurements) and _last(run.measurements[cursor]) <= now:
            fleet.push("v", run.measurements[cursor])
            cursor += 1
        parts += [rows for _, rows in fleet.advance({"v": now})]
    rows = np.concatenate(parts)
    t_s = (rows["stamp_ns"] - run.start_ns) / 1e9
    mu_true = np.interp(t_s, run.truth.t_s, run.truth.mu)
    in_turn = (t_s > 12.0) & (t_s < 14.0)
    assert np.all(np.abs(rows["mu_filter"][in_turn] / mu_true[in_turn] - 1.0) < 0.06)
    informed = (rows["flags"] & FrictionFlag.INFORMED) > 0
    assert np.all(np.abs(rows["mu"][informed] / mu_true[informed] - 1.0) < 0.1)


def _steady_awd_turn(vy_bias_mps: float) -> tuple[TickInputs, Chassis, TyreArrays]:
    """One tick of an all-wheel-drive car in a steady turn at 12 m/s on μ 0.5, its four tyres
    at 41-54 % of the grip (slip angles 7-11 mrad, κ 2e-3), measured through the filter's own
    model; the GNSS lateral speed is the truth's 0.15 m/s plus ``vy_bias_mps`` with a 1-σ of
    0.03 m/s (a bias the filter cannot see), and the speed's shared κ error is 1e-3 (no
    undriven rim reads the speed)."""
    cfg = FOUR_WHEEL_CONFIG
    chassis = Chassis.of([cfg])
    t = cfg.tyre
    tyres = TyreArrays(
        *(np.array([[v]]) for v in (t.kz_npm, t.unloaded_radius_m, t.c_px_npm2, t.c_py_npm2))
    )
    fz = np.array([[5200.0, 7600.0, 4800.0, 7000.0]])
    kappa = np.full((1, 4), 2e-3)
    delta = np.array([[0.04, 0.04, 0.0, 0.0]])
    vx, vy, r = 12.0, 0.15, 0.2
    for _ in range(50):  # the yaw rate of a steady turn: r = a_y / v_x
        alpha = _slip_angles(chassis, vx, vy, r, delta)
        cx, cy = tyres.stiffness(fz)
        fx, fy = brush_forces(kappa, alpha, fz, 0.5, cx, cy)
        z = body_accelerations(fx[:, None], fy[:, None], delta[:, None], chassis)[:, 0]
        r = float(z[0, 1]) / vx
    u = TickInputs(
        fz_n=fz,
        alpha_rad=alpha,
        delta_rad=delta,
        kappa=kappa,
        kappa_std=np.full((1, 4), 5e-4),
        kappa_common_std=np.array([1e-3]),
        alpha_std_rad=np.full((1, 4), 3e-3),
        z=np.array([[z[0, 0], z[0, 1], 0.0]]),
        valid=np.array([True]),
        vx_mps=np.array([vx]),
        yaw_rate_radps=np.array([r]),
        vy_meas_mps=np.array([vy + vy_bias_mps]),
        vy_meas_std_mps=np.array([0.03]),
        alpha_lag_rad=np.zeros((1, 4)),
        radius_m=np.full((1, 4), t.unloaded_radius_m),
        balance_std_n=np.full((1, 2), 1e6),
    )
    return u, chassis, tyres


def test_mu_upper_is_the_far_end_of_its_interval() -> None:
    """``ln μ`` 1-σ from the root's first row (two entries: √(0.3² + 0.4²) = 0.5), μ at
    ``+2σ``: 0.3 · e¹ by hand."""
    cfg = FilterConfig()
    x = np.zeros((1, len(ProductState)))
    x[0, ProductState.LN_MU] = math.log(0.3)
    s = np.zeros((1, len(ProductState), len(ProductState)))
    s[0, 0, 0], s[0, 0, 1] = 0.3, 0.4
    assert mu_upper(x, s, cfg)[0, 0] == pytest.approx(0.3 * math.e, rel=1e-12)


def test_a_biased_side_slip_does_not_press_mu_onto_its_floor() -> None:
    """An all-wheel-drive steady turn at half the grip whose lateral speed reads 0.1 m/s low:
    every slip angle reads ~8 mrad too large, which the brush model can only explain by
    saturated tyres, so the μ that fits is the body's ``|a|/g`` (0.24 here, the grip floor's
    0.23 under it). Judged at that μ, the tyres are at their limit, where the curve is flat
    in the slips: the gate opened and ``ln μ`` was pressed to 0.25 with a 1-σ of 3.4 %, its
    σ small only because a saturated tyre's force is ``μ F_z``. Judged at the far end of μ's
    interval the same slips leave the tyres in their linear range: μ is held at its prior,
    its 1-σ wide. With the lateral speed right, the same holds (half the grip does not tell μ
    from the stiffness)."""
    cfg = FilterConfig()
    for bias in (-0.1, 0.0):
        u, chassis, tyres = _steady_awd_turn(bias)
        st = initial_state(cfg, tyres, u.fz_n)
        assert _gain_mask(st.x, st.s, cfg, tyres, u)[0, ProductState.LN_MU] == 0
        for _ in range(200):
            st = filter_step(st, cfg, tyres, chassis, u)
        mu = float(mu_of(st.x[0, 0], cfg.mode))
        sd = float(np.linalg.norm(st.s[0, 0]))
        assert mu > 0.4, (bias, mu)
        assert sd > 0.1, (bias, sd)


def test_mu_waits_for_the_vehicles_first_steering_angle() -> None:
    """A turn whose steering stream starts ``LATE_STEERING_S`` into it (IMU, wheels and GNSS
    from the start): before the first angle no row is informed or updated, each says why
    (``NO_STEERING``) and the filter's μ stays its prior; from it on μ is learnt and informed
    within 10 % of the road's 0.4, as with the angle from the start."""
    run = simulate_four_wheel([TURN], seeds=[11])[0]
    late, first_ns = late_steering(run)
    fleet = FrictionFleet()
    fleet.add_vehicle("late", late.config)
    rows = _drive(fleet, [late], ["late"])["late"]
    before = rows["stamp_ns"] < first_ns
    flags = rows["flags"]
    assert before.sum() > 200 and (~before).sum() > 50
    assert ((flags[before] & FrictionFlag.NO_UPDATE) > 0).all()
    assert (rows["mu_filter"][before] == rows["mu_filter"][0]).all()
    assert not (flags[before] & FrictionFlag.INFORMED).any()
    assert np.isnan(rows["mu"][before]).all()
    assert ((flags[before] & FrictionFlag.NO_STEERING) > 0).all()
    assert not (flags[~before] & FrictionFlag.NO_STEERING).any()
    informed = (flags & FrictionFlag.INFORMED) > 0
    assert informed[~before].sum() > 25
    assert np.abs(rows["mu"][informed] / 0.4 - 1).max() < 0.1


def test_the_front_wheels_columns_are_empty_before_the_first_steering_angle() -> None:
    """Before the first angle the front pair's slip, slip angle and grip used are unknown
    (NaN, not computed with the wheels straight); the rear pair's and, from the first angle
    on, all four are known."""
    late, first_ns = late_steering(simulate_four_wheel([TURN], seeds=[11])[0])
    fleet = FrictionFleet()
    fleet.add_vehicle("late", late.config)
    rows = _drive(fleet, [late], ["late"])["late"]
    before = rows["stamp_ns"] < first_ns
    assert before.sum() > 200 and (~before).sum() > 50
    assert front_columns_empty(rows[before]).all()
    assert not front_columns_empty(rows[~before]).any()
    assert rear_columns_known(rows).all()


def test_mu_stops_learning_while_the_steering_stream_is_stalled() -> None:
    """A turn whose steering stream stops 1.4 s into it for 0.8 s: from ``steer_timeout_s`` after
    the last angle until the next, the held angle counts as none (``NO_STEERING``, no update,
    ``mu_filter`` held, the front pair's columns NaN); before and after, as with the stream
    whole, and μ is learnt and informed again within 10 % of the road's 0.4."""
    run, last_ns, resumed_ns = stalled_steering(simulate_four_wheel([TURN], seeds=[11])[0])
    fleet = FrictionFleet()
    fleet.add_vehicle("stalled", run.config)
    rows = _drive(fleet, [run], ["stalled"])["stalled"]
    timeout_ns = round(fleet.config.front.steer_timeout_s * 1e9)
    t, flags = rows["stamp_ns"], rows["flags"]
    stale = (t > last_ns + timeout_ns) & (t < resumed_ns)
    assert stale.sum() > 20 and (t >= resumed_ns).sum() > 40
    assert ((flags[stale] & FrictionFlag.NO_STEERING) > 0).all()
    assert ((flags[stale] & FrictionFlag.NO_UPDATE) > 0).all()
    assert not (flags[stale] & FrictionFlag.INFORMED).any()
    assert np.ptp(rows["mu_filter"][stale]) < 1e-9  # held (its log's round trip aside)
    assert front_columns_empty(rows[stale]).all() and rear_columns_known(rows).all()
    assert not (flags[~stale] & FrictionFlag.NO_STEERING).any()
    assert not front_columns_empty(rows[~stale]).any()
    informed = (flags & FrictionFlag.INFORMED) > 0
    assert informed[t < last_ns].sum() > 10 and informed[t >= resumed_ns].sum() > 10
    assert np.abs(rows["mu"][informed] / 0.4 - 1).max() < 0.1


def slow_steering(run: FourWheelRun, period_s: float, jitter_s: float) -> FourWheelRun:
    """``run`` with its steering angles thinned to one every ``period_s``, each stamp moved by
    up to ``±jitter_s`` (a slow CAN message on a busy bus), sent one sample a packet."""
    rng = np.random.default_rng(7)
    steering = [m for m in run.measurements if isinstance(m, SteeringAngles)]
    stamps = np.concatenate([m.stamp_ns for m in steering])
    angles = np.concatenate([m.angle_rad for m in steering])
    step = round(period_s * 1e9)
    grid = np.arange(stamps[0] + step, stamps[-1], step)
    grid += rng.integers(-round(jitter_s * 1e9), round(jitter_s * 1e9), grid.size)
    slow = [
        SteeringAngles(stamp_ns=np.array([t]), angle_rad=np.interp([t], stamps, angles))
        for t in grid
    ]
    kept = [m for m in run.measurements if not isinstance(m, SteeringAngles)]
    return dataclasses.replace(run, measurements=sorted(kept + slow, key=_first_stamp))


def _first_stamp(m: Measurement) -> int:
    return int(np.atleast_1d(m.stamp_ns)[0])


def test_a_live_10_hz_steering_stream_with_jitter_never_reads_as_stalled() -> None:
    """Steering angles at 10 Hz, each up to 30 ms early or late: the angle is never taken for
    a stalled stream (no ``NO_STEERING`` after the first), and μ is still learnt and informed
    within 10 % of the road's 0.4."""
    run = slow_steering(simulate_four_wheel([TURN], seeds=[11])[0], 0.1, 0.03)
    first = min(_first_stamp(m) for m in run.measurements if isinstance(m, SteeringAngles))
    fleet = FrictionFleet()
    fleet.add_vehicle("slow", run.config)
    rows = _drive(fleet, [run], ["slow"])["slow"]
    flags, after = rows["flags"], rows["stamp_ns"] >= first
    assert after.sum() > 100
    assert not (flags[after] & FrictionFlag.NO_STEERING).any()
    informed = (flags & FrictionFlag.INFORMED) > 0
    assert informed.sum() > 20
    assert np.abs(rows["mu"][informed] / 0.4 - 1).max() < 0.1
