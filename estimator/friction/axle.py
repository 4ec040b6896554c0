"""What a driven axle adds to the product filter's inputs: the open differential's torque
balance, and each slip's sensitivity to the load model (``method.md`` §5).

An open differential gives both wheels of its axle the same torque, so while they spin
steadily ``F_L r_L = F_R r_R`` (the wheels' inertia times their acceleration difference and the
differential's friction aside). The product filter carries it per axle as a pseudo-measurement
``h = (F_L r_L − F_R r_R) / r̄ = 0`` [N] (``r̄`` the axle's mean radius). It ties the two driven
forces together where the slips cannot: a soft tyre's radius sinks ``ρ/kz`` per newton of load,
five times a sound one's, so a small error of the load model is a large error of its slip
``κ`` (``ρ σ_Fz / (kz r_u)``, which :func:`load_slip_std` gives); with the slip's 1-σ honest
and the balance in the same update, the filter reads that tyre's force from its partner's and
the body's acceleration instead of from its slip.

The balance is applied (``σ`` finite) on an axle that drives through an open differential,
while the body is driven forward (``z``'s ``a_x`` positive: brakes are not one torque), both
wheels slip less than ``max_slip`` (traction control cuts one wheel's torque beyond) and the
lateral acceleration is below ``max_lateral_mps2``: in a turn the two slips' errors are the
lateral load transfer's and the yaw kinematics', correlated with ``ṙ``'s, and a balance read
there moved ``ṙ``'s reading and μ with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import Differential, DrivenAxle, Wheeled4wdSteeredConfig

__all__ = ["AxleArrays", "AxleConfig", "balance_std_n", "effective_radii_m", "load_slip_std"]

_AXLE_SHARE = {
    DrivenAxle.FRONT: (1.0, 0.0),
    DrivenAxle.REAR: (0.0, 1.0),
    DrivenAxle.ALL: (0.5, 0.5),
}


@dataclass(frozen=True, slots=True)
class AxleConfig:
    """The torque balance's noise and the load model's error.

    ``rel_std``: the balance's 1-σ per newton of a wheel's drive force (the differential's
    friction, ±2 % of the torque each side, and the radius ratio's error); ``floor_std_n``: its
    1-σ at no force (the wheels' inertia, ~1.5 kg·m² × 1 rad/s² / 0.33 m ≈ 5 N, and the rims'
    resolution); ``radius_drop``, ``radius_drop_std``: ``ρ`` of ``r_e = r_u − ρ Fz/kz`` (0.25-0.4
    for real tyres) and its 1-σ; ``max_slip``: the balance holds below it;
    ``load_std_n``: the load model's 1-σ per wheel (the front end's loads against the truth's,
    roll split and lag unknown: within 27 N, ``docs/perf/friction.md``);
    ``max_lateral_mps2``: the balance is applied below this lateral acceleration;
    ``weightless_std_n``: the 1-σ of a row not applied.
    """

    rel_std: float = 0.03
    floor_std_n: float = 30.0
    radius_drop: float = 1.0 / 3.0
    radius_drop_std: float = 0.05
    max_slip: float = 0.02
    max_lateral_mps2: float = 1.0
    load_std_n: float = 30.0
    weightless_std_n: float = 1e6


@dataclass(frozen=True, slots=True)
class AxleArrays:
    """Per vehicle ``(B, ·)``: unloaded radius ``(B, 1)``, mass ``(B,)`` and each axle's share
    of the drive force through an open differential ``(B, 2)`` (0 for an undriven axle or a
    locked differential)."""

    unloaded_radius_m: FloatArray
    mass_kg: FloatArray
    open_share: FloatArray

    @staticmethod
    def of(configs: list[Wheeled4wdSteeredConfig]) -> AxleArrays:
        ch = [c.chassis for c in configs]
        share = np.array(
            [
                _AXLE_SHARE[c.driven_axle] if c.differential is Differential.OPEN else (0.0, 0.0)
                for c in ch
            ]
        )
        return AxleArrays(
            unloaded_radius_m=np.array([[c.tyre.unloaded_radius_m] for c in configs]),
            mass_kg=np.array([c.mass_kg for c in ch], dtype=np.float64),
            open_share=share.reshape(len(configs), 2),
        )

    @staticmethod
    def concat(parts: list[AxleArrays]) -> AxleArrays:
        return AxleArrays(
            *(np.concatenate([getattr(p, n) for p in parts]) for n in AxleArrays.__slots__)
        )


def effective_radii_m(
    fz_n: FloatArray, kz_npm: FloatArray, axles: AxleArrays, cfg: AxleConfig
) -> FloatArray:
    """``r_e = r_u − ρ Fz/kz`` per wheel ``(B, 4)`` (only their ratio within an axle matters)."""
    radius: FloatArray = axles.unloaded_radius_m - cfg.radius_drop * fz_n / kz_npm
    return radius


def load_slip_std(
    fz_n: FloatArray, kz_npm: FloatArray, axles: AxleArrays, cfg: AxleConfig
) -> FloatArray:
    """κ's 1-σ ``(B, 4)`` from the load model's error: ``ρ σ_Fz / (kz r_u)`` (loads ``(B, 4)``
    broadcast; 1.2e-4 on a 250,000 N/m tyre, five times that on a 50,000 N/m one)."""
    std: FloatArray = cfg.radius_drop * cfg.load_std_n / (kz_npm * axles.unloaded_radius_m)
    std = np.broadcast_to(std, fz_n.shape).copy()
    return std


def balance_std_n(
    fz_n: FloatArray,
    kz_npm: FloatArray,
    kappa: FloatArray,
    z: FloatArray,
    axles: AxleArrays,
    cfg: AxleConfig,
) -> FloatArray:
    """The balance's 1-σ per axle ``(B, 2)`` [N] (``weightless_std_n`` where not applied), of
    loads, vertical stiffness and slips ``(B, 4)`` and the measured ``[a_x, a_y, ṙ]`` ``(B, 3)``.

    A wheel's drive force ``F ≈ m a_x · share / 2``; its error ``F · hypot(rel_std, σ_ρ Δd / r_u)``
    (``Δd`` the two tyres' deflection difference ``Fz/kz``, whose ``ρ`` is not known) in
    quadrature with ``floor_std_n``."""
    ax_mps2 = z[:, 0]
    force = (axles.mass_kg * np.maximum(ax_mps2, 0.0))[:, None] * axles.open_share / 2
    deflection = fz_n / kz_npm
    spread = np.abs(deflection[:, 0::2] - deflection[:, 1::2]) / axles.unloaded_radius_m
    rel = np.hypot(cfg.rel_std, cfg.radius_drop_std * spread)
    std = np.hypot(cfg.floor_std_n, force * rel)
    slip = np.maximum(np.abs(kappa[:, 0::2]), np.abs(kappa[:, 1::2]))
    straight = (ax_mps2 > 0) & (np.abs(z[:, 1]) < cfg.max_lateral_mps2)
    applied = (axles.open_share > 0) & straight[:, None] & (slip < cfg.max_slip)
    out: FloatArray = np.where(applied, std, cfg.weightless_std_n)
    return out
