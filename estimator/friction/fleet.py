"""The friction estimator as a ``FleetEstimator``: every vehicle's μ filter stepped together.

Each vehicle has its :class:`~.frontend.FrontEnd` (sensors → per-wheel inputs, per tick) and
one row of the batched filter (:func:`~.filter.filter_step`, vehicles × cubature points in one
numpy call per round). Ticks lie on ``first IMU sample + k·tick_s`` (or ``align_ticks``); a
tick is computed once the IMU covers it.

Informed or not (``method.md`` §5's warning): μ is told apart from stiffness only where the
tyres work in their non-linear range, and not at all without excitation. A tick is
``INFORMED`` when, over the last ``informed_hold_s``, every tick was updated with μ's relative
1-σ below ``informed_rel_std`` and the most used tyre at ``informed_min_util`` of its grip or
more, and μ moved less than ``informed_spread`` of itself (a filter still travelling is not
informed, however small its σ: its σ does not know the front end's correlated errors);
otherwise the row holds the last informed μ (``HELD``) and no σ. A tyre whose rolling radius
says it is softer or harder than the config's (``TYRE_SUSPECT``) has its own vertical
stiffness learnt by the front end, and so its own contact length and brush stiffness.
Each vehicle's position (:mod:`.position`) is placed by its GNSS fixes and dead-reckoned
between them from the row's speeds and the gyro; ``anchor``/``set_anchor`` give and take the
origin of its ENU frame. Rows: :data:`~estimator.friction_spec.FRICTION_SPEC`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from estimator._arrays import FloatArray
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
    ProductState,
    TickInputs,
    TyreArrays,
    _stiffness_of,
    filter_step,
    initial_state,
    mu_of,
    mu_std_of,
)
from estimator.friction.frontend import FrontEnd, FrontEndConfig, FrontEndTick
from estimator.friction.model import Chassis
from estimator.friction.position import PositionConfig, PositionTrack
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


class _Vehicle:
    def __init__(self, config: Wheeled4wdSteeredConfig, cfg: FrictionFleetConfig) -> None:
        self.config = config
        self.front = FrontEnd(config, cfg.front, cfg.filter.tick_s)
        self.position = PositionTrack(cfg.position)
        self.tick_ns = round(cfg.filter.tick_s * 1e9)
        self.next_ns: int | None = None
        self.state: FilterState | None = None
        self.held_mu = math.nan
        window = max(1, round(cfg.informed_hold_s / cfg.filter.tick_s))
        self.recent: deque[tuple[bool, float]] = deque(maxlen=window)
        ty = config.tyre
        self.tyres = TyreArrays(
            *(
                np.array([[v]])
                for v in (ty.kz_npm, ty.unloaded_radius_m, ty.c_px_npm2, ty.c_py_npm2)
            )
        )
        self.chassis = Chassis.of([config])
        self.axles = AxleArrays.of([config])

    def due(self, until_ns: int) -> list[int]:
        last = self.front.imu_until_ns()
        if last is None:
            return []
        if self.next_ns is None:
            self.next_ns = int(self.front.imu[0][0][0]) + self.tick_ns
        end = min(until_ns, last)
        if end < self.next_ns:
            return []
        n = (end - self.next_ns) // self.tick_ns + 1
        ticks = [self.next_ns + k * self.tick_ns for k in range(n)]
        self.next_ns = ticks[-1] + self.tick_ns
        return ticks


_GNSS_VY_STD_MPS = 0.1
"""1-σ of GNSS lateral speed (velocity noise and the heading's across a 20 m/s velocity)."""


def _cat(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(parts, axis=0)


def _place(row: np.ndarray, track: PositionTrack, t_ns: int, fe: FrontEndTick) -> FrictionFlag:
    """Fill the row's position from the vehicle's track (stepped with the row's speeds and the
    gyro's yaw rate); its ``DEAD_RECKONED`` bit."""
    here = track.step(t_ns, fe.vx_mps, float(row["vy_mps"].item()), fe.yaw_rate_radps)
    row["east_m"] = here.east_m
    row["north_m"] = here.north_m
    row["up_m"] = here.up_m
    row["heading_rad"] = here.heading_rad
    return FrictionFlag.DEAD_RECKONED if here.dead_reckoned else FrictionFlag.NONE


def _stack_inputs(fes: list[FrontEndTick], axles: AxleArrays, cfg: AxleConfig) -> TickInputs:
    """One :class:`TickInputs` of the vehicles' front-end ticks, one row each, with the driven
    axles' torque balance and κ's 1-σ widened by the load model's error (:mod:`.axle`)."""
    fz = np.stack([fe.fz_n for fe in fes])
    kz = np.stack([fe.kz_npm for fe in fes])
    kappa = np.stack([fe.kappa for fe in fes])
    z = np.stack([fe.z for fe in fes])
    return TickInputs(
        fz_n=fz,
        alpha_rad=np.stack([fe.alpha_rad for fe in fes]),
        delta_rad=np.stack([fe.delta_rad for fe in fes]),
        kappa=kappa,
        kappa_std=np.hypot(
            np.stack([fe.kappa_std for fe in fes]), load_slip_std(fz, kz, axles, cfg)
        ),
        kappa_common_std=np.array([fe.kappa_common_std for fe in fes]),
        alpha_std_rad=np.stack([fe.alpha_std_rad for fe in fes]),
        z=z,
        valid=np.array([fe.valid for fe in fes]),
        vx_mps=np.array([fe.vx_mps for fe in fes]),
        yaw_rate_radps=np.array([fe.yaw_rate_radps for fe in fes]),
        vy_meas_mps=np.array([fe.vy_gnss_mps for fe in fes]),
        vy_meas_std_mps=np.full(len(fes), _GNSS_VY_STD_MPS),
        alpha_lag_rad=np.stack([fe.alpha_lag_rad for fe in fes]),
        radius_m=effective_radii_m(fz, kz, axles, cfg),
        balance_std_n=balance_std_n(fz, kz, kappa, z, axles, cfg),
    )


class FrictionFleet:
    """Many vehicles' friction estimators behind one batched step (a ``FleetEstimator``)."""

    name = "friction"
    spec = FRICTION_SPEC
    output_dtype = FRICTION_SPEC.dtype

    def __init__(self, config: FrictionFleetConfig | None = None) -> None:
        self.config = config or FrictionFleetConfig()
        self._vehicles: dict[str, _Vehicle] = {}

    def add_vehicle(self, vehicle_id: str, config: VehicleConfig) -> None:
        steered = expect_kind(config, Wheeled4wdSteeredConfig, self.name)
        self._vehicles[vehicle_id] = _Vehicle(steered, self.config)

    def remove_vehicle(self, vehicle_id: str) -> None:
        self._vehicles.pop(vehicle_id, None)

    def vehicle_ids(self) -> list[str]:
        return list(self._vehicles)

    def push(self, vehicle_id: str, measurement: Pushed) -> None:
        front = self._vehicles[vehicle_id].front
        if isinstance(measurement, ImuBatch):
            front.push_imu(measurement)
        elif isinstance(measurement, WheelSpeeds4):
            front.push_wheels(measurement)
        elif isinstance(measurement, SteeringAngles):
            front.push_steering(measurement)
        elif isinstance(measurement, GnssSample):
            front.push_gnss(measurement)
            self._vehicles[vehicle_id].position.push(measurement)

    def align_ticks(self, vehicle_id: str, stamp_ns: int) -> None:
        v = self._vehicles[vehicle_id]
        if v.next_ns is None:
            v.next_ns = int(stamp_ns)

    def anchor(self, vehicle_id: str) -> tuple[float, float, float] | None:
        """``(lat_deg, lon_deg, height_m)`` of the vehicle's ENU frame (its first fix's
        antenna), None before it."""
        return self._vehicles[vehicle_id].position.anchor()

    def set_anchor(self, vehicle_id: str, lat_deg: float, lon_deg: float, height_m: float) -> None:
        """Give the vehicle's ENU frame this origin (the one its stored rows are in) instead
        of its first fix; ``ValueError`` for what is no geodetic position."""
        self._vehicles[vehicle_id].position.set_anchor(lat_deg, lon_deg, height_m)

    def advance(self, until_ns: Mapping[str, int]) -> list[tuple[str, np.ndarray]]:
        """Emit every tick with ``stamp_ns <= until_ns[vehicle_id]`` the IMU covers."""
        work: list[tuple[str, _Vehicle, list[tuple[int, FrontEndTick]]]] = []
        for vid, until in until_ns.items():
            v = self._vehicles.get(vid)
            if v is None:
                continue
            ticks = [(t, v.front.tick(t)) for t in v.due(int(until))]
            ready = [(t, fe) for t, fe in ticks if fe is not None]
            if ready:
                work.append((vid, v, ready))
        if not work:
            return []
        out = [FRICTION_SPEC.empty_rows(len(w[2])) for w in work]
        for r in range(max(len(w[2]) for w in work)):
            part = [k for k, w in enumerate(work) if len(w[2]) > r]
            self._round(
                [work[k][1] for k in part],
                [work[k][2][r] for k in part],
                [out[k][r : r + 1] for k in part],
            )
        return [(w[0], rows) for w, rows in zip(work, out, strict=True)]

    def _round(
        self, vs: list[_Vehicle], ticks: list[tuple[int, FrontEndTick]], rows: list[np.ndarray]
    ) -> None:
        """Step one tick of every vehicle in ``vs`` together."""
        axles = AxleArrays.concat([v.axles for v in vs])
        u = _stack_inputs([fe for _, fe in ticks], axles, self.config.axle)
        tyres = TyreArrays(
            kz_npm=np.stack([fe.kz_npm for _, fe in ticks]),
            radius_m=_cat([v.tyres.radius_m for v in vs]),
            c_px_npm2=_cat([v.tyres.c_px_npm2 for v in vs]),
            c_py_npm2=_cat([v.tyres.c_py_npm2 for v in vs]),
        )
        chassis = Chassis(
            mass_kg=_cat([v.chassis.mass_kg for v in vs]),
            yaw_inertia_kgm2=_cat([v.chassis.yaw_inertia_kgm2 for v in vs]),
            wheel_x_m=_cat([v.chassis.wheel_x_m for v in vs]),
            wheel_y_m=_cat([v.chassis.wheel_y_m for v in vs]),
        )
        fresh = [v.state is None for v in vs]
        st = filter_step(self._states(vs, tyres, u), self.config.filter, tyres, chassis, u)
        util = self._utilisation(st, tyres, u)
        for i, v in enumerate(vs):
            v.state = st.take(np.array([i]))
            self._row(rows[i], v, ticks[i], st, i, util[i], fresh[i])

    def _states(self, vs: list[_Vehicle], tyres: TyreArrays, u: TickInputs) -> FilterState:
        """The vehicles' filter states stacked; a vehicle's first tick starts from the prior."""
        prior = initial_state(self.config.filter, tyres, u.fz_n)
        own = [prior.take(np.array([i])) if v.state is None else v.state for i, v in enumerate(vs)]
        return FilterState(
            x=_cat([s.x for s in own]),
            s=_cat([s.s for s in own]),
            fz_prev_n=_cat([s.fz_prev_n for s in own]),
            nis=_cat([s.nis for s in own]),
        )

    def _utilisation(self, st: FilterState, tyres: TyreArrays, u: TickInputs) -> FloatArray:
        """Grip used per wheel ``(B, 4)`` at the filter's mean state."""
        mean = st.x[:, None, :]
        cx, cy = _stiffness_of(mean, self.config.filter, tyres, u.fz_n)
        mu = mu_of(st.x[:, :1], self.config.filter.mode)
        fx, fy = brush_forces(u.kappa, u.alpha_rad, u.fz_n, mu, cx[:, 0], cy[:, 0])
        return utilisation(fx, fy, u.fz_n, mu)

    def _informed(
        self, v: _Vehicle, updated: bool, mu: float, std: float, util: FloatArray
    ) -> bool:
        """This tick and the last ``informed_hold_s`` met the informed conditions."""
        cfg = self.config
        ok = (
            updated
            and std / mu < cfg.informed_rel_std
            and (float(np.nanmax(util)) >= cfg.informed_min_util)
        )
        v.recent.append((ok, mu))
        if len(v.recent) < (v.recent.maxlen or 1) or not all(o for o, _ in v.recent):
            return False
        mus = [m for _, m in v.recent]
        return (max(mus) - min(mus)) / mu < cfg.informed_spread

    def _row(
        self,
        row: np.ndarray,
        v: _Vehicle,
        tick: tuple[int, FrontEndTick],
        st: FilterState,
        i: int,
        util: FloatArray,
        fresh: bool,
    ) -> None:
        t_ns, fe = tick
        mode = self.config.filter.mode
        mu = float(mu_of(st.x[i, 0], mode))
        std = float(mu_std_of(st.x[i, 0], float(np.linalg.norm(st.s[i, 0])), mode))
        informed = self._informed(v, bool(st.updated[i]), mu, std, util)
        flags = FrictionFlag.NONE
        if informed:
            v.held_mu = mu
            flags |= FrictionFlag.INFORMED
        else:
            flags |= FrictionFlag.HELD
        if not st.updated[i]:
            flags |= FrictionFlag.NO_UPDATE
        if fe.gnss:
            flags |= FrictionFlag.GNSS_SPEED
        if fe.tyre_suspect:
            flags |= FrictionFlag.TYRE_SUSPECT
        if self.config.filter.mode is FrictionMode.PAPER and st.updated[i] and not st.mee_ok[i]:
            flags |= FrictionFlag.MEE_FALLBACK
        if fresh:
            flags |= FrictionFlag.RESET
        row["stamp_ns"] = t_ns
        row["mu"] = mu if informed else v.held_mu
        row["mu_std"] = std if informed else math.nan
        row["mu_filter"] = mu
        row["vx_mps"] = fe.vx_mps
        row["vy_mps"] = st.x[i, ProductState.VY] if mode is FrictionMode.PRODUCT else fe.vy_mps
        for j, key in enumerate(WHEEL_KEYS):
            row[f"fz_{key}_n"] = fe.fz_n[j]
            row[f"slip_{key}_pct"] = 100.0 * fe.kappa[j]
            row[f"alpha_{key}_rad"] = fe.alpha_rad[j]
            row[f"util_{key}_pct"] = 100.0 * util[j]
        row["flags"] = int(flags | _place(row, v.position, t_ns, fe))
