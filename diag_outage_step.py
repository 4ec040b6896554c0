"""Diagnosis of the MDSF outage step test (issue 25): per-tick log of the test's window.

Run from the worktree with its PYTHONPATH:
    python diag_outage_step.py named gnss_outage '{"outage_s": 40.0}' OUT.npz [window_s]
    python diag_outage_step.py drive SEED K OUT.npz [window_s]
    python diag_outage_step.py test OUT.npz [window_s]   (the banked U-turn, one antenna)
Logs per tick of an outage: stamp, the newest r, V1, ωz, bias, the step level; per test the
fit's coefficients (StepCol order), z, found; and the product rows and the truth.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np

import estimator.mdsf.engine as eng
from estimator.mdsf import MdsfConfig, MdsfFleet, MdsfMode
from estimator.mdsf.outage_step import StepBuf, StepCol, step_columns
from estimator.sim import replay, simulate
from estimator.sim.drives import draw_drive
from server.tooling.bench.accuracy import (
    START_NS,
    _radii_from_a_calibration_drive,
    evaluate,
    run_estimator,
)

LOG: dict[str, list] = {"tick": [], "fit": []}
_orig_test = eng.step_test
_orig_steps = eng.MdsfEngine._outage_slip_steps
_NOW = [0]


def _theta(buf, dt_s, prior):
    """The test's ridge fit, its coefficients and posterior std (the same math as step_test)."""
    a = step_columns(buf, dt_s)
    w = buf[:, StepBuf.OK]
    r = np.where(w > 0, buf[:, StepBuf.R], 0.0)
    inv = np.zeros(len(StepCol))
    inv[StepCol.TURN_LOAD] = prior.load_s**-2
    inv[StepCol.TURN_YAW] = prior.yaw_rad**-2
    inv[StepCol.TURN_CENT] = prior.cent_m**-2
    inv[StepCol.STEP] = prior.step**-2
    for col, name in (("TILT_SIN", "tilt_rad"), ("TILT_COS", "tilt_rad"), ("GAIN", "gain")):
        if hasattr(StepCol, col):
            inv[StepCol[col]] = getattr(prior, name) ** -2
    ata = np.einsum("kni,kn,knj->kij", a, w, a)
    atr = np.einsum("kni,kn,kn->ki", a, w, r)
    dof = np.maximum(w.sum(axis=1) - len(StepCol), 1.0)
    var = np.full(buf.shape[0], prior.noise_floor_mps**2)
    for _ in range(3):
        cov = np.linalg.inv(ata + var[:, None, None] * np.diag(inv)[None])
        th = np.einsum("kij,kj->ki", cov, atr)
        res = r - np.einsum("kni,ki->kn", a, th)
        var = np.maximum((w * res * res).sum(axis=1) / dof, prior.noise_floor_mps**2)
    return th, np.sqrt(var[:, None] * np.diagonal(cov, axis1=1, axis2=2)), np.sqrt(var), a


def _test(buf, dt_s, prior):
    fit = _orig_test(buf, dt_s, prior)
    th, sd, noise, a = _theta(buf, dt_s, prior)
    for j in range(buf.shape[0]):
        LOG["fit"].append(
            dict(
                stamp_ns=_NOW[0],
                theta=th[j].tolist(),
                sd=sd[j].tolist(),
                noise=float(noise[j]),
                z=float(fit.z[j]),
                found=bool(fit.found[j]),
                delta=float(fit.delta[j]),
                r=buf[j, StepBuf.R].tolist(),
                v1=buf[j, StepBuf.V1].tolist(),
                yaw=buf[j, StepBuf.YAW].tolist(),
                contrib=(a[j] * th[j]).T.tolist(),
            )
        )
    return fit


def _steps(self, slots, t, z, x_prior, up, lost, rim_mps, rim_ok):
    _NOW[0] = int(t.stamp_ns[0])
    out = _orig_steps(self, slots, t, z, x_prior, up, lost, rim_mps, rim_ok)
    if lost[0]:
        b = self.step_buf[slots[0]]
        x = up.x
        v_wheel = np.einsum("kmi,ki->km", up.H[:, eng._RIM, : eng.MdsfState.ACCEL_BIAS], x[:, :4])
        lever = v_wheel.mean(axis=1)[0] - x[0, eng.MdsfState.V1]
        level = (
            self.slip_anchor[slots].mean(axis=1) + self._demand_slip(slots) + self.step_level[slots]
        )[0]
        rim_mean = np.where(rim_ok, rim_mps, 0.0).mean(axis=1)[0]
        LOG["tick"].append(
            [
                _NOW[0],
                b[StepBuf.R, -1],
                b[StepBuf.V1, -1],
                b[StepBuf.YAW, -1],
                b[StepBuf.BIAS, -1],
                self.step_level[slots[0]],
                self.step_inertial[slots[0]],
                float(out[0]),
                rim_mean,
                lever,
                level,
                x[0, eng.MdsfState.V1],
            ]
        )
    return out


eng.step_test = _test
eng.MdsfEngine._outage_slip_steps = _steps


def main() -> None:
    kind = sys.argv[1]
    if kind == "named":
        name, kw, out = sys.argv[2], json.loads(sys.argv[3]), sys.argv[4]
        rest = sys.argv[5:]
        sim = simulate(name, seed=1, start_ns=START_NS, **kw)
        prepare = None
    elif kind == "drive":
        seed, k, out = int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
        rest = sys.argv[5:]
        d = draw_drive(seed, k)
        sim = simulate(
            "random_drive", seed=d.sim_seed, start_ns=START_NS, config=d.config(), **d.overrides
        )
        prepare = "drive"
    elif kind == "fw6":
        out, rest = sys.argv[2], sys.argv[3:]
        sim = simulate(
            "field_work",
            seed=1,
            start_ns=START_NS,
            gnss_outages=((60.0, 85.0),),
            slip_steps=((70.0, 6.0, 0.0),),
        )
        prepare = "replay"
    else:
        out, rest = sys.argv[2], sys.argv[3:]
        sim = simulate(
            "field_work",
            seed=1,
            start_ns=START_NS,
            duration_s=80.0,
            bank_roll_deg=6.0,
            gnss_outages=((30.0, 60.0),),
            gnss_attitude=False,
        )
        prepare = None
    window = float(rest[0]) if rest else 6.0
    cfg = dataclasses.replace(sim.config, noise=sim.sensor_noise)
    prep = _radii_from_a_calibration_drive(d, cfg) if prepare == "drive" else None
    fleet = MdsfFleet(MdsfConfig(mode=MdsfMode.PRODUCT, outage_step_window_s=window))
    if prepare == "replay":  # fed as tests/estimator/test_mdsf_outage_step.py feeds it
        fleet.add_vehicle("v", cfg)
        parts = []
        for chunk, until in replay(sim.measurements, step_ns=100_000_000, end_ns=sim.end_ns):
            for m in chunk:
                fleet.push("v", m)
            parts += [r for _, r in fleet.advance({"v": until})]
        rows = np.concatenate(parts)
    else:
        rows = run_estimator(fleet, sim, cfg, prepare=prep)
    m = evaluate(rows, sim.truth)
    deg = evaluate(rows[(rows["flags"] & 2) != 0], sim.truth)
    print(json.dumps({k: round(v, 3) for k, v in m.items()}))
    print("outage rows", json.dumps({k: round(v, 3) for k, v in deg.items()}))
    np.savez(
        out,
        tick=np.array(LOG["tick"]),
        fit=np.array(json.dumps(LOG["fit"])),
        rows=rows,
        truth=sim.truth,
    )


if __name__ == "__main__":
    main()
