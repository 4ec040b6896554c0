"""MCAP files and ROS 1/2 bags for ``slipfleet import`` (message types: ``docs/import.md``).

Read messages, by type (a topic of each chosen by option when a log has several):

==========================================================  ================================
``sensor_msgs/msg/Imu``                                     IMU: ``linear_acceleration``,
                                                            ``angular_velocity``
``sensor_msgs/msg/NavSatFix``                               GNSS position and fix
``geometry_msgs/msg/TwistWithCovarianceStamped`` or         GNSS velocity, ENU (x east,
``geometry_msgs/msg/TwistStamped``                          y north, z up)
``sensor_msgs/msg/JointState``                              wheel speeds: ``velocity`` of the
                                                            left and right wheel joints
==========================================================  ================================

Every sample is stamped with its message's ``header.stamp`` (the sensor time, not the time the
bag recorded it). ROS bodies are x forward, y left, z up (REP 103); the product's are X right,
Y forward, Z up, so IMU vectors become ``(-y, x, z)``. A fix takes the velocity stamped
identically (NaN without one; ``vel_std_mps`` is the root of the east variance when the
covariance gives one); NavSatFix status ``-1/0/1/2`` reads as no fix, single, DGNSS, RTK fixed.
MCAP files hold ROS 2 messages (``cdr``, schemas ``ros2msg``); a ROS 2 bag is a directory
(SQLite or MCAP storage), a ROS 1 bag a ``.bag`` file (both read by ``rosbags``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from estimator.types import GnssFix, GnssSample
from server.tooling.importer_log import ImportedLog, LogBuilder, LogError

__all__ = ["MSG_TYPES", "Message", "TopicChoice", "read_bag", "read_mcap"]

IMU = "sensor_msgs/msg/Imu"
FIX = "sensor_msgs/msg/NavSatFix"
TWIST_COV = "geometry_msgs/msg/TwistWithCovarianceStamped"
TWIST = "geometry_msgs/msg/TwistStamped"
JOINTS = "sensor_msgs/msg/JointState"
#: What each read message type becomes.
MSG_TYPES = {IMU: "imu", FIX: "fix", TWIST_COV: "vel", TWIST: "vel", JOINTS: "wheels"}
#: NavSatFix ``status.status`` → fix type.
FIX_OF_STATUS = {
    -1: GnssFix.NONE,
    0: GnssFix.SINGLE,
    1: GnssFix.DGNSS,
    2: GnssFix.RTK_FIXED,
}


@dataclass(frozen=True, slots=True)
class Message:
    """One deserialised message: its topic, type, number in the log (from 1) and content."""

    topic: str
    msgtype: str
    index: int
    msg: Any

    @property
    def where(self) -> str:
        return f"message {self.index} on {self.topic}"


@dataclass(frozen=True)
class TopicChoice:
    """Which topic feeds each role (None: the one topic of its type) and the wheel joints
    (None: the first joint named with ``left`` and the first with ``right``)."""

    imu: str | None = None
    fix: str | None = None
    vel: str | None = None
    wheels: str | None = None
    wheel_joints: tuple[str, str] | None = None


def _pick(topics: dict[str, str], role: str, given: str | None) -> str | None:
    """The topic of ``role`` among ``topics`` (topic → role)."""
    candidates = sorted(t for t, r in topics.items() if r == role)
    if given is not None:
        if given not in topics:
            raise LogError(f"no topic {given!r} of a {role} message type in the log")
        return given
    if len(candidates) > 1:
        raise LogError(
            f"{len(candidates)} {role} topics ({', '.join(candidates)}): choose one with "
            f"--{role}-topic"
        )
    return candidates[0] if candidates else None


def chosen_topics(types: dict[str, str], choice: TopicChoice) -> dict[str, str]:
    """Topic → role of the topics to read (``types``: every topic's message type)."""
    roles = {t: MSG_TYPES[m] for t, m in types.items() if m in MSG_TYPES}
    out = {}
    for role in ("imu", "fix", "vel", "wheels"):
        topic = _pick(roles, role, getattr(choice, role))
        if topic is not None:
            out[topic] = role
    return out


def _stamp_ns(m: Message) -> int:
    stamp = m.msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _flu_to_rfu(v: Any) -> tuple[float, float, float]:
    """A ROS body vector (x forward, y left, z up) in the product's body frame."""
    return (-float(v.y), float(v.x), float(v.z))


def _wheel_columns(m: Message, joints: tuple[str, str] | None) -> tuple[int, int]:
    names = [str(n) for n in m.msg.name]
    if joints is not None:
        missing = [j for j in joints if j not in names]
        if missing:
            raise LogError(f"{m.where}: no joint {missing[0]!r} among {names}")
        return names.index(joints[0]), names.index(joints[1])
    left = next((i for i, n in enumerate(names) if "left" in n.lower()), None)
    right = next((i for i, n in enumerate(names) if "right" in n.lower()), None)
    if left is None or right is None:
        raise LogError(f"{m.where}: no left and right wheel joints among {names} (--wheel-joints)")
    return left, right


@dataclass
class _Collector:
    """Turns messages into samples of a :class:`LogBuilder`."""

    choice: TopicChoice
    builder: LogBuilder = field(default_factory=LogBuilder)
    fixes: list[tuple[int, Message]] = field(default_factory=list)
    velocities: dict[int, tuple[tuple[float, float, float], float]] = field(default_factory=dict)

    def take(self, role: str, m: Message) -> None:
        stamp = _stamp_ns(m)
        if role == "imu":
            accel, gyro = (
                _flu_to_rfu(m.msg.linear_acceleration),
                _flu_to_rfu(m.msg.angular_velocity),
            )
            self.builder.add_imu(stamp, accel, gyro, m.where)
        elif role == "wheels":
            left, right = _wheel_columns(m, self.choice.wheel_joints)
            velocity = list(m.msg.velocity)
            if len(velocity) <= max(left, right):
                raise LogError(f"{m.where}: JointState without the wheels' velocity")
            self.builder.add_wheels(stamp, float(velocity[left]), float(velocity[right]), m.where)
        elif role == "fix":
            self.fixes.append((stamp, m))
        else:
            self.velocities[stamp] = _velocity(m)

    def build(self) -> ImportedLog:
        nan3 = (math.nan, math.nan, math.nan)
        for stamp, m in self.fixes:
            vel, vel_std = self.velocities.get(stamp, (nan3, math.nan))
            self.builder.add_gnss(_fix_sample(stamp, m, vel, vel_std), m.where)
        return self.builder.build()


def _velocity(m: Message) -> tuple[tuple[float, float, float], float]:
    """ENU velocity of a twist message and its 1-sigma per axis (NaN if not given)."""
    twist = m.msg.twist
    if m.msgtype == TWIST_COV:
        var_e = float(twist.covariance[0])
        lin = twist.twist.linear
        return (float(lin.x), float(lin.y), float(lin.z)), math.sqrt(
            var_e
        ) if var_e > 0 else math.nan
    lin = twist.linear
    return (float(lin.x), float(lin.y), float(lin.z)), math.nan


def _fix_sample(
    stamp: int, m: Message, vel: tuple[float, float, float], vel_std: float
) -> GnssSample:
    status = int(m.msg.status.status)
    fix = FIX_OF_STATUS.get(status)
    if fix is None:
        raise LogError(f"{m.where}: NavSatFix status {status} is not one of -1, 0, 1, 2")
    nan = math.nan
    return GnssSample(
        stamp,
        vel,
        nan,
        nan,
        nan,
        float(m.msg.latitude),
        float(m.msg.longitude),
        float(m.msg.altitude),
        fix,
        vel_std,
    )


def _collect(
    types: dict[str, str], messages: Iterable[Message], choice: TopicChoice, roles: dict[str, str]
) -> ImportedLog:
    collector = _Collector(choice)
    for m in messages:
        role = roles.get(m.topic)
        if role is not None:
            try:
                collector.take(role, m)
            except (AttributeError, TypeError, ValueError) as exc:
                if isinstance(exc, LogError):
                    raise
                raise LogError(f"{m.where}: not a readable {m.msgtype} ({exc})") from None
    if not roles:
        raise LogError(f"no topic of {sorted(MSG_TYPES)} in the log (topics: {types})")
    return collector.build()


def read_bag(path: Path, choice: TopicChoice) -> ImportedLog:
    """The samples of a ROS 1 bag (``.bag``) or a ROS 2 bag (a directory)."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    try:
        with AnyReader([path]) as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
            roles = chosen_topics(types, choice)
            wanted = [c for c in reader.connections if c.topic in roles]

            def messages() -> Iterator[Message]:
                for i, (conn, _, raw) in enumerate(reader.messages(connections=wanted), 1):
                    yield Message(
                        conn.topic, conn.msgtype, i, reader.deserialize(raw, conn.msgtype)
                    )

            return _collect(types, messages(), choice, roles)
    except (AnyReaderError, OSError) as exc:
        raise LogError(f"cannot read {path} as a ROS bag: {exc}") from None


def _mcap_types(reader: Any) -> tuple[dict[str, str], dict[int, str]]:
    """Topic → message type, channel id → topic of an MCAP summary."""
    summary = reader.get_summary()
    if summary is None:
        raise LogError("the MCAP file has no summary (unfinished file?)")
    types, topic_of = {}, {}
    for cid, channel in summary.channels.items():
        schema = summary.schemas.get(channel.schema_id)
        types[channel.topic] = schema.name if schema is not None else ""
        topic_of[cid] = channel.topic
    return types, topic_of


def read_mcap(path: Path, choice: TopicChoice) -> ImportedLog:
    """The samples of an MCAP file of ROS 2 messages (CDR)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    try:
        with open(path, "rb") as fh:
            reader = make_reader(fh)
            types, _ = _mcap_types(reader)
            roles = chosen_topics(types, choice)

            def messages() -> Iterator[Message]:
                for i, (schema, channel, msg) in enumerate(
                    reader.iter_messages(topics=list(roles)), 1
                ):
                    if channel.message_encoding != "cdr" or schema is None:
                        raise LogError(f"message {i} on {channel.topic}: not a ROS 2 CDR message")
                    yield Message(
                        channel.topic,
                        schema.name,
                        i,
                        typestore.deserialize_cdr(msg.data, schema.name),
                    )

            return _collect(types, messages(), choice, roles)
    except (McapError, OSError) as exc:
        raise LogError(f"cannot read {path} as MCAP: {exc}") from None
