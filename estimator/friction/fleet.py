"""The friction estimator as a ``FleetEstimator``: every vehicle's μ filter stepped together.

Each vehicle has a slot of the sensor rows (:class:`~.sensors.FleetSensors`: every vehicle's
due ticks of a call read in one vectorised pass), of the batched front end
(:class:`~.fleetfront.FleetFrontEnd`: sensors → per-wheel inputs, every vehicle of a round in
one numpy pass) and one row of the batched filter (:func:`~.filter.filter_step`, vehicles ×
cubature points in one numpy call per round); its constants, filter state and informed window
live in :class:`~.slots.FleetSlots`. Ticks lie on ``first IMU sample + k·tick_s`` (or
``align_ticks``); a tick is computed once the IMU covers it.

Informed or not (``method.md`` §5's warning): μ is told apart from stiffness only where the
tyres work in their non-linear range, and not at all without excitation. A tick is
``INFORMED`` when, over the last ``informed_hold_s``, every tick was updated with μ's relative
1-σ below ``informed_rel_std`` and the most used tyre at ``informed_min_util`` of its grip or
more (judged at the far end of μ's interval, :func:`~.filter.mu_upper`: at the mean, a μ
pulled low finds the tyres at their limit by itself), and μ moved less than
``informed_spread`` of itself (a filter still travelling is not informed, however small its
σ: its σ does not know the front end's correlated errors);
otherwise the row holds the last informed μ (``HELD``) and no σ. A tyre whose rolling radius
says it is softer or harder than the config's (``TYRE_SUSPECT``) has its own vertical
stiffness learnt by the front end, and so its own contact length and brush stiffness.
Each vehicle's position (:mod:`.position`) is placed by its GNSS fixes and dead-reckoned
between them from the row's speeds and the gyro; ``anchor``/``set_anchor`` give and take the
origin of its ENU frame. Rows: :data:`~estimator.friction_spec.FRICTION_SPEC`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from estimator._arrays import BoolArray, FloatArray, IntArray
from estimator.base import Pushed
from estimator.config import ConfigError, VehicleConfig, Wheeled4wdSteeredConfig, expect_kind
from estimator.friction.axle import (
    AxleArrays,
    AxleConfig,
    balance_std_n,
    effective_radii_m,
    load_slip_std,
)
from estimator.friction.brush import brush_forces, utilisation
from estimator.friction.filter import (
    FilterConfig,
    FilterState,
    FrictionMode,
    PaperState,
    ProductState,
    TickInputs,
    TyreArrays,
    _stiffness_of,
    _tyres_subset,
    filter_step,
    initial_state,
    mu_of,
    mu_std_of,
    mu_upper,
    reported_mu_std,
)
from estimator.friction.fleetfront import FleetFrontEnd, FrontEndTicks
from estimator.friction.frontend import FrontEndConfig, antenna_velocity_at_cg
from estimator.friction.position import FleetPositions, PositionConfig
from estimator.friction.sensors import FleetSensors
from estimator.friction.slots import FleetSlots
from estimator.friction_spec import FRICTION_SPEC, WHEEL_KEYS, FrictionFlag
from estimator.types import GnssSample, ImuBatch, SteeringAngles, WheelSpeeds4

__all__ = ["FrictionFleet", "FrictionFleetConfig"]


@dataclass(frozen=True, slots=True)
class FrictionFleetConfig:
    """Settings of the friction estimator: the filter (and its mode), the front end, the
    position track, the driven axles' torque balance and the slips' load sensitivity (product
    mode), and when μ counts as informed (relative 1-σ below ``informed_rel_std`` and the most
    used tyre at ``informed_min_util`` of its grip or more)."""

    filter: FilterConfig = field(default_factory=FilterConfig)
    frontend: FrontEndConfig | None = None
    position: PositionConfig = field(default_factory=PositionConfig)
    axle: AxleConfig = field(default_factory=AxleConfig)
    informed_rel_std: float = 0.03
    informed_min_util: float = 0.6
    informed_hold_s: float = 0.5
    informed_spread: float = 0.03

    def __post_init__(self) -> None:
        if not 0.005 <= self.filter.tick_s <= 0.2:
            raise ConfigError(f"tick_s must be within 0.005..0.2 s, got {self.filter.tick_s!r}")
        if not (0 < self.informed_rel_std < 1 and 0 <= self.informed_min_util <= 1):
            raise ConfigError("informed_rel_std must be in (0, 1), informed_min_util in [0, 1]")

    @property
    def front(self) -> FrontEndConfig:
        """The front end: the paper's reading for every mode but the product's."""
        if self.frontend is not None:
            return self.frontend
        return FrontEndConfig(paper=self.filter.mode is not FrictionMode.PRODUCT)


@dataclass(frozen=True, slots=True)
class _Vehicle:
    config: Wheeled4wdSteeredConfig
    slot: int


_GNSS_VY_STD_MPS = 0.1
"""1-σ of GNSS lateral speed (velocity noise and the heading's across a 20 m/s velocity)."""


def _tick_inputs(fe: FrontEndTicks, axles: AxleArrays, cfg: AxleConfig) -> TickInputs:
    """The filter's :class:`TickInputs` of a round's front-end output, with the driven axles'
    torque balance and κ's 1-σ widened by the load model's error (:mod:`.axle`)."""
    return TickInputs(
        fz_n=fe.fz_n,
        alpha_rad=fe.alpha_rad,
        delta_rad=fe.delta_rad,
        kappa=fe.kappa,
        kappa_std=np.hypot(fe.kappa_std, load_slip_std(fe.fz_n, fe.kz_npm, axles, cfg)),
        kappa_common_std=fe.kappa_common_std,
        alpha_std_rad=fe.alpha_std_rad,
        z=fe.z,
        valid=fe.valid,
        vx_mps=fe.vx_mps,
        yaw_rate_radps=fe.yaw_rate_radps,
        vy_meas_mps=fe.vy_gnss_mps,
        vy_meas_std_mps=np.full(fe.vx_mps.size, _GNSS_VY_STD_MPS),
        alpha_lag_rad=fe.alpha_lag_rad,
        radius_m=effective_radii_m(fe.fz_n, fe.kz_npm, axles, cfg),
        balance_std_n=balance_std_n(fe.fz_n, fe.kz_npm, fe.kappa, fe.z, axles, cfg),
    )


def _front_columns(out: np.ndarray, at: IntArray, fe: FrontEndTicks, util: FloatArray) -> None:
    """The rows ``out[at]``'s front-end columns (speed and its 1-σ, per-wheel load, slip, slip
    angle) and the grip used ``util`` ``(B, 4)``, for the whole round at once."""
    out["vx_mps"][at] = fe.vx_mps
    out["vx_std_mps"][at] = fe.vx_std_mps
    for j, key in enumerate(WHEEL_KEYS):
        out[f"fz_{key}_n"][at] = fe.fz_n[:, j]
        out[f"slip_{key}_pct"][at] = 100.0 * fe.kappa[:, j]
        out[f"alpha_{key}_rad"][at] = fe.alpha_rad[:, j]
        out[f"util_{key}_pct"][at] = 100.0 * util[:, j]


class FrictionFleet:
    """Many vehicles' friction estimators behind one batched step (a ``FleetEstimator``)."""

    name = "friction"
    spec = FRICTION_SPEC
    output_dtype = FRICTION_SPEC.dtype

    def __init__(self, config: FrictionFleetConfig | None = None) -> None:
        self.config = config or FrictionFleetConfig()
        self._vehicles: dict[str, _Vehicle] = {}
        self._front = FleetFrontEnd(self.config.front, self.config.filter.tick_s)
        self._positions = FleetPositions(self.config.position)
        front = self.config.front
        self._sensors = FleetSensors(
            round(self.config.filter.tick_s * 1e9), front.gnss_timeout_s, front.steer_timeout_s
        )
        self._free_slots: list[int] = []
        window = max(1, round(self.config.informed_hold_s / self.config.filter.tick_s))
        self._slots = FleetSlots(_n_state(self.config.filter.mode), window)

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        steered = expect_kind(config, Wheeled4wdSteeredConfig, self.name)
        old = self._vehicles.get(vehicle_id)
        if old is not None:
            slot = old.slot
        elif self._free_slots:
            slot = self._free_slots.pop()
        else:
            slot = len(self._vehicles)
        self._front.add(slot, steered)
        self._positions.add(slot)
        self._slots.reset(slot, steered)
        self._sensors.add(slot)
        self._vehicles[vehicle_id] = _Vehicle(steered, slot)

    def remove_vehicle(self, vehicle_id: str) -> None:
        v = self._vehicles.pop(vehicle_id, None)
        if v is not None:
            self._free_slots.append(v.slot)

    def vehicle_ids(self) -> list[str]:
        return list(self._vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        slot = self._vehicles[vehicle_id].slot
        if isinstance(measurement, ImuBatch):
            self._sensors.push_imu(slot, measurement)
        elif isinstance(measurement, WheelSpeeds4):
            self._sensors.push_wheels(slot, measurement)
        elif isinstance(measurement, SteeringAngles):
            self._sensors.push_steering(slot, measurement)
        elif isinstance(measurement, GnssSample):
            self._sensors.push_gnss(slot, measurement)
            self._positions.push(slot, measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        self._sensors.align(self._vehicles[vehicle_id].slot, int(stamp_ns))

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's ENU frame (its first fix's
        antenna), None before it."""
        return self._positions.anchor(self._vehicles[vehicle_id].slot)

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the vehicle's ENU frame this origin (the one its stored rows are in) instead
        of its first fix; ``ValueError`` for what is no geodetic position."""
        self._positions.set_anchor(self._vehicles[vehicle_id].slot, lat_deg, lon_deg, height_m)

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every tick with ``stamp_ns <= until_ns[vehicle_id]`` the IMU covers."""
        ids = [vid for vid in until_ns if vid in self._vehicles]
        if not ids:
            return []
        slots = np.array([self._vehicles[vid].slot for vid in ids])
        until = np.array([until_ns[vid] for vid in ids], dtype=np.int64)
        every, counts = self._sensors.read(slots, until)
        have = np.flatnonzero(counts)
        if not have.size:
            return []
        ids = [ids[i] for i in have.tolist()]
        slots, counts = slots[have], counts[have]
        starts = np.cumsum(counts) - counts
        out = FRICTION_SPEC.empty_rows(int(counts.sum()))  # each vehicle's rows in a run
        for r in range(int(counts.max())):
            part = np.flatnonzero(counts > r)
            at = starts[part] + r
            sensed = every.take(at)
            fe = self._front.step(slots[part], sensed)
            self._round(slots[part], sensed.t_ns, fe, out, at)
            self._place(out, at, slots[part], sensed.t_ns, fe)
        return [
            (vid, out[a : a + n])
            for vid, a, n in zip(ids, starts.tolist(), counts.tolist(), strict=True)
        ]

    def _place(
        self, out: np.ndarray, at: IntArray, s: IntArray, t_ns: IntArray, fe: FrontEndTicks
    ) -> None:
        """The rows ``out[at]``'s position from the vehicles' tracks, stepped with the antenna's
        speeds (the rows' CG speeds moved through its lever arm) and the gyro's yaw rate; their
        ``DEAD_RECKONED`` bit."""
        cg = np.stack([fe.vx_mps, out["vy_mps"][at]], axis=1)
        rates = np.column_stack([fe.roll_pitch_rate_radps, fe.yaw_rate_radps])
        arm = self._front.car.antenna_arm[s]
        vx, vy = antenna_velocity_at_cg(cg, rates, -arm).T  # v_cg + ω × r
        enu, heading, late = self._positions.step(s, t_ns, vx, vy, fe.yaw_rate_radps)
        out["east_m"][at], out["north_m"][at], out["up_m"][at] = enu.T
        out["heading_rad"][at] = heading
        out["flags"][at] |= np.where(late, int(FrictionFlag.DEAD_RECKONED), 0).astype(
            out["flags"].dtype
        )

    def _round(
        self, s: IntArray, t_ns: IntArray, fe: FrontEndTicks, out: np.ndarray, at: IntArray
    ) -> None:
        """Step one tick of the vehicles in slots ``s`` together (``fe``: their front ends'),
        into the rows ``out[at]``."""
        u = _tick_inputs(fe, self._slots.axles_of(s), self.config.axle)
        tyres, chassis = self._slots.constants(s, fe.kz_npm)
        fresh = ~self._slots.has_state[s]
        prior = initial_state(self.config.filter, _tyres_subset(tyres, fresh), u.fz_n[fresh])
        st = filter_step(self._slots.states(s, prior, fresh), self.config.filter, tyres, chassis, u)
        self._slots.keep(s, st)
        _front_columns(out, at, fe, self._utilisation(st, tyres, u))
        far = self._utilisation(st, tyres, u, mu_upper(st.x, st.s, self.config.filter))
        self._rows(out, at, s, (t_ns, fe), st, far, fresh)

    def _utilisation(
        self, st: FilterState, tyres: TyreArrays, u: TickInputs, mu: FloatArray | None = None
    ) -> FloatArray:
        """Grip used per wheel ``(B, 4)`` at the filter's mean state (at ``mu`` ``(B, 1)``
        instead of its mean μ where given)."""
        mean = st.x[:, None, :]
        cx, cy = _stiffness_of(mean, self.config.filter, tyres, u.fz_n)
        if mu is None:
            mu = mu_of(st.x[:, :1], self.config.filter.mode)
        fx, fy = brush_forces(u.kappa, u.alpha_rad, u.fz_n, mu, cx[:, 0], cy[:, 0])
        return utilisation(fx, fy, u.fz_n, mu)

    def _rows(
        self,
        out: np.ndarray,
        at: IntArray,
        s: IntArray,
        tick: tuple[IntArray, FrontEndTicks],
        st: FilterState,
        util: FloatArray,
        fresh: BoolArray,
    ) -> None:
        """The rows ``out[at]``'s μ (informed, or the last informed held), its 1-σ and flags, for
        the round's vehicles in slots ``s`` at once."""
        t_ns, fe = tick
        cfg = self.config
        mode = cfg.filter.mode
        mu = mu_of(st.x[:, 0], mode)
        root_row = st.s[:, 0]
        std = mu_std_of(st.x[:, 0], np.sqrt(np.einsum("ij,ij->i", root_row, root_row)), mode)
        ok = st.updated & (std / mu < cfg.informed_rel_std)
        ok &= np.fmax.reduce(util, axis=1) >= cfg.informed_min_util
        informed = self._slots.informed(s, ok, mu, cfg.informed_spread)
        self._slots.held_mu[s[informed]] = mu[informed]
        out["stamp_ns"][at] = t_ns
        reported = np.where(informed, mu, self._slots.held_mu[s])
        out["mu"][at] = reported
        out["mu_std"][at] = reported_mu_std(reported, mu, std)
        out["mu_filter"][at] = mu
        out["vy_mps"][at] = st.x[:, ProductState.VY] if mode is FrictionMode.PRODUCT else fe.vy_mps
        out["flags"][at] = _flags(informed, st, fe, fresh, mode)


def _n_state(mode: FrictionMode) -> int:
    """Length of the filter's state in ``mode``."""
    return len(ProductState) if mode is FrictionMode.PRODUCT else len(PaperState)


def _flags(
    informed: BoolArray, st: FilterState, fe: FrontEndTicks, fresh: BoolArray, mode: FrictionMode
) -> IntArray:
    """Each row's :class:`FrictionFlag` bits ``(B,)``."""
    bits = [
        (informed, FrictionFlag.INFORMED),
        (~informed, FrictionFlag.HELD),
        (~st.updated, FrictionFlag.NO_UPDATE),
        (fe.gnss, FrictionFlag.GNSS_SPEED),
        (~fe.steering, FrictionFlag.NO_STEERING),
        (fe.tyre_suspect, FrictionFlag.TYRE_SUSPECT),
        (fresh, FrictionFlag.RESET),
    ]
    if mode is FrictionMode.PAPER:
        bits.append((st.updated & ~st.mee_ok, FrictionFlag.MEE_FALLBACK))
    flags = np.zeros(informed.size, dtype=np.int64)
    for where, flag in bits:
        flags |= np.where(where, int(flag), 0)
    return flags
