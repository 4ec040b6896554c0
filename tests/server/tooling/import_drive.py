"""One simulated drive written as other systems log it: a CSV of the product's columns, a ROS 2
bag (``rosbags``' writer) and an MCAP file (``mcap``'s writer, ROS 2 CDR messages), and the
same drive's wire packets as the vehicle sends them over Zenoh.

The drive is :func:`estimator.sim.simulate`'s: its GNSS epochs (single antenna: no attitude, so
NavSatFix and a twist carry all of an epoch) and IMU batches, and wheel speeds from its truth
(the CAN bus of a tractor: angular speed, 100 Hz, with noise).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from estimator.config import WheeledRearDriveConfig
from estimator.types import GnssSample, ImuBatch, WheelSpeeds

__all__ = ["Drive", "make_drive", "write_csv", "write_mcap", "write_ros2_bag"]

NS = 1_000_000_000
STATUS_OF_FIX = {0: -1, 1: 0, 2: 1, 4: 2}  # GnssFix → NavSatFix status


@dataclass(frozen=True)
class Drive:
    """A drive's samples, the vehicle's config, and its packets in the order sent."""

    config: WheeledRearDriveConfig
    gnss: list[GnssSample]
    imu: list[ImuBatch]
    wheels: WheelSpeeds


def make_drive(start_ns: int, seed: int = 5) -> Drive:
    """The simulator's figure eight (one lap), IMU as it batches it, wheel speeds of truth."""
    import dataclasses

    from estimator.sim import simulate

    run = simulate("figure_eight", seed=seed, start_ns=start_ns, laps=1, gnss_attitude=False)
    truth = run.truth
    rng = np.random.default_rng(seed)
    omega = np.column_stack([truth["omega_left_radps"], truth["omega_right_radps"]])
    omega = omega + rng.normal(0.0, 0.01, omega.shape)
    config = dataclasses.replace(run.config, noise=run.sensor_noise)
    return Drive(
        config=config,
        gnss=[m for m in run.measurements if isinstance(m, GnssSample)],
        imu=[m for m in run.measurements if isinstance(m, ImuBatch)],
        wheels=WheelSpeeds(np.asarray(truth["stamp_ns"], dtype=np.int64), omega),
    )


def imu_samples(drive: Drive) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every IMU sample: stamps, specific force ``(n, 3)``, angular rate ``(n, 3)``."""
    return (
        np.concatenate([b.stamp_ns for b in drive.imu]),
        np.concatenate([b.accel_mps2 for b in drive.imu]),
        np.concatenate([b.gyro_radps for b in drive.imu]),
    )


def _cell(x: float) -> str:
    return "" if math.isnan(x) else repr(float(x))


def write_csv(drive: Drive, path: Path) -> None:
    """The product's documented columns (``docs/import.md``), one sample a row, streams
    interleaved by time, times as integer ns."""
    header = ["stream", "stamp_ns", "accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]
    header += ["gyro_x_radps", "gyro_y_radps", "gyro_z_radps", "lat_deg", "lon_deg", "height_m"]
    header += ["vel_east_mps", "vel_north_mps", "vel_up_mps", "fix", "vel_std_mps"]
    header += ["omega_left_radps", "omega_right_radps"]
    rows: list[tuple[int, dict[str, str]]] = []
    t, acc, gyr = imu_samples(drive)
    for i in range(len(t)):
        vals = [*acc[i], *gyr[i]]
        rows.append((int(t[i]), dict(zip(header[2:8], map(_cell, vals), strict=True))))
        rows[-1][1]["stream"] = "imu"
    for g in drive.gnss:
        vals = [g.lat_deg, g.lon_deg, g.height_m, *g.vel_enu_mps]
        cells = dict(zip(header[8:14], map(_cell, vals), strict=True))
        rows.append((g.stamp_ns, {**cells, "stream": "gnss", "fix": str(int(g.fix))}))
        rows[-1][1]["vel_std_mps"] = _cell(g.vel_std_mps)
    w = drive.wheels
    for i in range(len(w.stamp_ns)):
        cells = dict(zip(header[16:], map(_cell, w.omega_radps[i]), strict=True))
        rows.append((int(w.stamp_ns[i]), {**cells, "stream": "wheels"}))
    rows.sort(key=lambda r: r[0])
    with open(path, "w", newline="") as fh:
        out = csv.DictWriter(fh, header)
        out.writeheader()
        for stamp, cells in rows:
            out.writerow({**cells, "stamp_ns": str(stamp)})


def ros_messages(drive: Drive, typestore: Any) -> list[tuple[str, str, int, Any]]:
    """``(topic, type, stamp_ns, message)`` of the drive as ROS 2 messages, in time order:
    IMU in the ROS body frame (x forward, y left), wheel speeds as a JointState."""
    T = typestore.types
    Time, Header, Vec = (
        T["builtin_interfaces/msg/Time"],
        T["std_msgs/msg/Header"],
        T["geometry_msgs/msg/Vector3"],
    )

    def header(stamp: int, frame: str) -> Any:
        return Header(stamp=Time(sec=stamp // NS, nanosec=stamp % NS), frame_id=frame)

    def flu(v: np.ndarray) -> Any:  # product (right, forward, up) → ROS (forward, left, up)
        return Vec(x=float(v[1]), y=-float(v[0]), z=float(v[2]))

    out: list[tuple[str, str, int, Any]] = []
    t, acc, gyr = imu_samples(drive)
    zero9 = np.zeros(9)
    for i in range(len(t)):
        msg = T["sensor_msgs/msg/Imu"](
            header=header(int(t[i]), "imu"),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.full(9, -1.0),
            angular_velocity=flu(gyr[i]),
            angular_velocity_covariance=zero9,
            linear_acceleration=flu(acc[i]),
            linear_acceleration_covariance=zero9,
        )
        out.append(("/imu/data", "sensor_msgs/msg/Imu", int(t[i]), msg))
    for g in drive.gnss:
        out.extend(_gnss_messages(T, header, g))
    w = drive.wheels
    for i in range(len(w.stamp_ns)):
        stamp = int(w.stamp_ns[i])
        msg = T["sensor_msgs/msg/JointState"](
            header=header(stamp, "base_link"),
            name=["front_axle", "rear_left_wheel_joint", "rear_right_wheel_joint"],
            position=np.zeros(3),
            velocity=np.array([0.0, w.omega_radps[i, 0], w.omega_radps[i, 1]]),
            effort=np.zeros(0),
        )
        out.append(("/wheels/joint_states", "sensor_msgs/msg/JointState", stamp, msg))
    out.sort(key=lambda m: m[2])
    return out


def _gnss_messages(T: Any, header: Any, g: GnssSample) -> list[tuple[str, str, int, Any]]:
    fix = T["sensor_msgs/msg/NavSatFix"](
        header=header(g.stamp_ns, "gnss"),
        status=T["sensor_msgs/msg/NavSatStatus"](status=STATUS_OF_FIX[int(g.fix)], service=1),
        latitude=g.lat_deg,
        longitude=g.lon_deg,
        altitude=g.height_m,
        position_covariance=np.zeros(9),
        position_covariance_type=0,
    )
    cov = np.zeros(36)
    cov[0] = g.vel_std_mps**2 if not math.isnan(g.vel_std_mps) else 0.0
    twist = T["geometry_msgs/msg/TwistWithCovarianceStamped"](
        header=header(g.stamp_ns, "gnss"),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](*map(float, g.vel_enu_mps)),
                angular=T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
            ),
            covariance=cov,
        ),
    )
    return [
        ("/gnss/fix", "sensor_msgs/msg/NavSatFix", g.stamp_ns, fix),
        ("/gnss/vel", "geometry_msgs/msg/TwistWithCovarianceStamped", g.stamp_ns, twist),
    ]


def write_ros2_bag(drive: Drive, path: Path) -> None:
    """The drive as a ROS 2 bag (a directory, SQLite storage) by ``rosbags``' own writer."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    messages = ros_messages(drive, typestore)
    with Writer(path, version=9) as writer:
        conns = {}
        for topic, msgtype, _, _ in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
        for topic, msgtype, stamp, msg in messages:
            writer.write(conns[topic], stamp, typestore.serialize_cdr(msg, msgtype))


def write_mcap(drive: Drive, path: Path) -> None:
    """The drive as an MCAP file of ROS 2 messages by ``mcap``'s own writer."""
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    messages = ros_messages(drive, typestore)
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="ros2", library="slipfleet-tests")
        channels: dict[str, int] = {}
        for topic, msgtype, _, _ in messages:
            if topic not in channels:
                text, _ = typestore.generate_msgdef(msgtype, ros_version=2)
                schema = writer.register_schema(msgtype, "ros2msg", text.encode())
                channels[topic] = writer.register_channel(topic, "cdr", schema)
        for topic, msgtype, stamp, msg in messages:
            data = bytes(typestore.serialize_cdr(msg, msgtype))
            writer.add_message(channels[topic], log_time=stamp, data=data, publish_time=stamp)
        writer.finish()
