"""Planar four-wheel vehicle model of the friction filter (``method.md`` §5, source 004 eq. 1-6).

Frame: x forward, y left, z up, origin at the centre of gravity (the ISO vehicle frame; the
IMU's body frame is x right, y forward, so ``a_y,left = −accel[:, 0]``). Wheels in
:class:`~estimator.types.Corner` order (front left, front right, rear left, rear right) at
``(x_i, y_i) = (lf, bf/2), (lf, −bf/2), (−lr, br/2), (−lr, −br/2)``.

Each wheel's brush forces ``(Fx, Fy)`` in its own frame (steered by ``δ_i``) turn into the body
frame and sum to the planar accelerations and the yaw acceleration:

    m a_x = Σ (Fx cos δ − Fy sin δ),   m a_y = Σ (Fx sin δ + Fy cos δ),
    I_z ṙ = Σ (x_i F_y,i − y_i F_x,i)   (body-frame components)

Drag and rolling resistance are known forces the front end adds back to the measured ``a_x``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from estimator._arrays import FloatArray
from estimator.config import Wheeled4wdSteeredConfig

__all__ = ["Chassis", "Measured", "Wheel4", "body_accelerations"]

GRAVITY_MPS2 = 9.80665


class Wheel4(IntEnum):
    """Column of a wheel in every per-wheel array of the friction estimator."""

    FL = 0
    FR = 1
    RL = 2
    RR = 3


class Measured(IntEnum):
    """Rows of the measurement vector ``z``."""

    AX = 0
    AY = 1
    YAW_ACCEL = 2


@dataclass(frozen=True, slots=True)
class Chassis:
    """A vehicle's numbers as arrays the batched model reads (one row per vehicle).

    ``wheel_x_m``, ``wheel_y_m`` ``(B, 4)``; the rest ``(B,)`` or ``(B, 1)`` where they
    broadcast against wheels.
    """

    mass_kg: FloatArray
    yaw_inertia_kgm2: FloatArray
    wheel_x_m: FloatArray
    wheel_y_m: FloatArray

    @staticmethod
    def of(configs: list[Wheeled4wdSteeredConfig]) -> Chassis:
        ch = [c.chassis for c in configs]
        lf = np.array([c.cg_to_front_axle_m for c in ch])
        lr = np.array([c.cg_to_rear_axle_m for c in ch])
        bf = np.array([c.front_track_m for c in ch]) / 2.0
        br = np.array([c.rear_track_m for c in ch]) / 2.0
        return Chassis(
            mass_kg=np.array([c.mass_kg for c in ch]),
            yaw_inertia_kgm2=np.array([c.yaw_inertia_kgm2 for c in ch]),
            wheel_x_m=np.stack([lf, lf, -lr, -lr], axis=-1),
            wheel_y_m=np.stack([bf, -bf, br, -br], axis=-1),
        )


def body_accelerations(
    fx_n: FloatArray, fy_n: FloatArray, delta_rad: FloatArray, chassis: Chassis
) -> FloatArray:
    """``[a_x, a_y, ṙ]`` ``(B, P, 3)`` of wheel forces ``(B, P, 4)`` steered by ``δ`` ``(B, 1, 4)``.

    ``P`` is the cubature-point axis; the chassis arrays broadcast as ``(B, 1, ·)``.
    """
    cos_d, sin_d = np.cos(delta_rad), np.sin(delta_rad)
    fxb = fx_n * cos_d - fy_n * sin_d
    fyb = fx_n * sin_d + fy_n * cos_d
    m = chassis.mass_kg[:, None]
    x = chassis.wheel_x_m[:, None, :]
    y = chassis.wheel_y_m[:, None, :]
    yaw = (x * fyb - y * fxb).sum(axis=-1) / chassis.yaw_inertia_kgm2[:, None]
    return np.stack([fxb.sum(axis=-1) / m, fyb.sum(axis=-1) / m, yaw], axis=-1)
