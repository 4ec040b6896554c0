"""A log read from another system: IMU, GNSS and wheel-speed samples with their origin.

Every reader of :mod:`server.tooling.importer` (CSV, Parquet, MCAP, ROS bags) adds samples to a
:class:`LogBuilder`, each with *where* it came from (a row number, a message number), and
:meth:`LogBuilder.build` sorts each stream by sensor time into an :class:`ImportedLog`. The
samples are in the product's conventions (``docs/protocol.md``): UTC nanoseconds, body frame X
right, Y forward, Z up, ENU velocity, wheel angular speed forward positive.

:func:`packets_of` cuts the log into the wire packets a vehicle would send (IMU and wheel
speeds in batches, one GNSS epoch per packet), checked by the server's own decoder, so the
first sample the server would refuse is named before anything is written.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from estimator._arrays import FloatArray, IntArray
from estimator.types import GnssSample, ImuBatch, WheelSpeeds
from server.protocol.codec import (
    DecodeError,
    EncodeError,
    decode,
    encode_gnss,
    encode_imu,
    encode_wheel_speeds,
)
from server.protocol.keys import Stream, sensor_key
from server.protocol.streams import spec_of

__all__ = [
    "ImportedLog",
    "LogBuilder",
    "LogError",
    "WirePacket",
    "packets_of",
]


class LogError(ValueError):
    """A log that cannot be imported; the message is one line naming the first bad row or
    message."""


@dataclass(slots=True)
class _Column:
    """One stream's samples as they are read: stamps, values (rows) and where each came from."""

    label: str
    width: int
    stamp_ns: list[int] = field(default_factory=list)
    values: list[tuple[float, ...]] = field(default_factory=list)
    where: list[str] = field(default_factory=list)

    def add(self, stamp_ns: int, values: tuple[float, ...], where: str) -> None:
        self.stamp_ns.append(stamp_ns)
        self.values.append(values)
        self.where.append(where)

    def sorted(self) -> tuple[IntArray, FloatArray, list[str]]:
        """Stamps (int64, increasing), values ``(n, k)`` and origins in sensor-time order;
        LogError when two samples share a stamp."""
        stamps = np.asarray(self.stamp_ns, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        values = np.asarray(self.values, dtype=np.float64).reshape(-1, self.width)[order]
        where = [self.where[int(i)] for i in order]
        repeat = np.flatnonzero(np.diff(stamps) == 0)
        if repeat.size:
            i = int(repeat[0])
            raise LogError(f"{where[i + 1]}: {self.label} stamp repeats that of {where[i]}")
        return stamps, values, where


class LogBuilder:
    """Collects samples of every stream in any order (see the module docstring)."""

    def __init__(self) -> None:
        self._imu = _Column("IMU", 6)
        self._wheels = _Column("wheel-speed", 2)
        self._gnss: list[tuple[GnssSample, str]] = []

    def add_imu(
        self,
        stamp_ns: int,
        accel_mps2: tuple[float, float, float],
        gyro_radps: tuple[float, float, float],
        where: str,
    ) -> None:
        """One IMU sample: specific force and angular rate in the body frame."""
        self._imu.add(stamp_ns, (*accel_mps2, *gyro_radps), where)

    def add_wheels(self, stamp_ns: int, left_radps: float, right_radps: float, where: str) -> None:
        """One wheel-speed sample: the driven wheels' angular speeds, forward positive."""
        self._wheels.add(stamp_ns, (left_radps, right_radps), where)

    def add_gnss(self, sample: GnssSample, where: str) -> None:
        """One GNSS epoch."""
        self._gnss.append((sample, where))

    def build(self) -> ImportedLog:
        """The log, each stream in sensor-time order (LogError on a repeated stamp)."""
        imu_t, imu_v, imu_w = self._imu.sorted()
        wh_t, wh_v, wh_w = self._wheels.sorted()
        gnss = sorted(self._gnss, key=lambda sw: sw[0].stamp_ns)
        for (a, wa), (b, wb) in itertools.pairwise(gnss):
            if a.stamp_ns == b.stamp_ns:
                raise LogError(f"{wb}: GNSS stamp repeats that of {wa}")
        return ImportedLog(
            imu=ImuBatch(imu_t, imu_v[:, :3].reshape(-1, 3), imu_v[:, 3:].reshape(-1, 3)),
            imu_where=imu_w,
            wheels=WheelSpeeds(wh_t, wh_v.reshape(-1, 2)),
            wheels_where=wh_w,
            gnss=[s for s, _ in gnss],
            gnss_where=[w for _, w in gnss],
        )


@dataclass(frozen=True)
class ImportedLog:
    """Every sample of a log, each stream sorted by sensor time (``stamp_ns`` increasing).

    ``*_where`` say where each sample came from (``"row 12"``, ``"message 7 on /imu"``)."""

    imu: ImuBatch
    imu_where: list[str]
    wheels: WheelSpeeds
    wheels_where: list[str]
    gnss: list[GnssSample]
    gnss_where: list[str]

    def counts(self) -> dict[str, int]:
        """Samples per stream (streams without any left out)."""
        n = {
            Stream.IMU.value: len(self.imu.stamp_ns),
            Stream.GNSS.value: len(self.gnss),
            Stream.WHEELS.value: len(self.wheels.stamp_ns),
        }
        return {k: v for k, v in n.items() if v}

    def span_ns(self) -> tuple[int, int] | None:
        """First and last stamp over every stream; None for an empty log."""
        firsts, lasts = [], []
        for stamps in (self.imu.stamp_ns, self.wheels.stamp_ns):
            if len(stamps):
                firsts.append(int(stamps[0]))
                lasts.append(int(stamps[-1]))
        if self.gnss:
            firsts.append(self.gnss[0].stamp_ns)
            lasts.append(self.gnss[-1].stamp_ns)
        return (min(firsts), max(lasts)) if firsts else None


@dataclass(frozen=True, slots=True)
class WirePacket:
    """One packet as a vehicle would publish it: key, payload, and the sensor time that
    completes it (its last sample's stamp: the order a live link delivers packets in)."""

    key: str
    payload: bytes
    last_stamp_ns: int
    stream: Stream


def _batches(n: int, size: int) -> list[slice]:
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


@dataclass(frozen=True, slots=True)
class _Made:
    """A packet with the origin of each of its samples and how to encode sample ``i`` alone
    (to name the one the decoder refuses)."""

    packet: WirePacket
    where: list[str]
    alone: Callable[[int], bytes]


def _imu_packets(log: ImportedLog, key: str, batch: int, seq0: int) -> list[_Made]:
    imu, out = log.imu, []
    for k, s in enumerate(_batches(len(imu.stamp_ns), batch)):
        part = ImuBatch(imu.stamp_ns[s], imu.accel_mps2[s], imu.gyro_radps[s])

        def alone(i: int, p: ImuBatch = part) -> bytes:
            return encode_imu(
                ImuBatch(p.stamp_ns[i : i + 1], p.accel_mps2[i : i + 1], p.gyro_radps[i : i + 1]), 0
            )

        packet = WirePacket(key, encode_imu(part, seq0 + k), int(part.stamp_ns[-1]), Stream.IMU)
        out.append(_Made(packet, log.imu_where[s], alone))
    return out


def _wheel_packets(log: ImportedLog, key: str, batch: int, seq0: int) -> list[_Made]:
    wheels, out = log.wheels, []
    for k, s in enumerate(_batches(len(wheels.stamp_ns), batch)):
        part = WheelSpeeds(wheels.stamp_ns[s], wheels.omega_radps[s])

        def alone(i: int, p: WheelSpeeds = part) -> bytes:
            return encode_wheel_speeds(
                WheelSpeeds(p.stamp_ns[i : i + 1], p.omega_radps[i : i + 1]), 0
            )

        payload = encode_wheel_speeds(part, seq0 + k)
        packet = WirePacket(key, payload, int(part.stamp_ns[-1]), Stream.WHEELS)
        out.append(_Made(packet, log.wheels_where[s], alone))
    return out


def _gnss_packets(log: ImportedLog, key: str, seq0: int) -> list[_Made]:
    out = []
    for k, (g, where) in enumerate(zip(log.gnss, log.gnss_where, strict=True)):
        payload = encode_gnss(g, seq0 + k)

        def alone(i: int, p: bytes = payload) -> bytes:
            return p

        out.append(_Made(WirePacket(key, payload, g.stamp_ns, Stream.GNSS), [where], alone))
    return out


def _refusal(made: _Made, prefix: str) -> str | None:
    """None when the server's decoder takes the packet; else one line naming the first sample
    it refuses (each sample decoded alone) and why."""
    key = made.packet.key
    try:
        decode(key, made.packet.payload, prefix=prefix, max_payload_bytes=1 << 30)
        return None
    except DecodeError as whole:
        first: tuple[str, DecodeError] = (made.where[0], whole)
    for i, where in enumerate(made.where):
        try:
            decode(key, made.alone(i), prefix=prefix, max_payload_bytes=1 << 30)
        except DecodeError as alone:
            first = (where, alone)
            break
    return f"{first[0]}: {made.packet.stream.value} sample refused ({first[1]})"


def packets_of(
    log: ImportedLog,
    vehicle_id: str,
    *,
    prefix: str = "fleet",
    batch: int = 10,
    first_seq: dict[Stream, int] | None = None,
) -> list[WirePacket]:
    """The wire packets of ``log`` in the order a live link delivers them (by the sensor time
    that completes each, then the streams' reorder priority).

    IMU and wheel-speed samples go ``batch`` to a packet (a vehicle sending 100 Hz in 100 ms
    batches: 10), starting with each stream's first sample; a GNSS epoch is one packet.
    ``first_seq`` gives each stream's first sequence number (default 0). Every packet is
    decoded by the server's own decoder: LogError names the first sample of the first packet
    it would refuse, with the reason.
    """
    if batch < 1:
        raise ValueError("batch must be >= 1")
    seq = first_seq or {}

    def key(stream: Stream) -> str:
        return sensor_key(prefix, vehicle_id, stream)

    try:
        made = [
            *_imu_packets(log, key(Stream.IMU), batch, seq.get(Stream.IMU, 0)),
            *_wheel_packets(log, key(Stream.WHEELS), batch, seq.get(Stream.WHEELS, 0)),
            *_gnss_packets(log, key(Stream.GNSS), seq.get(Stream.GNSS, 0)),
        ]
    except EncodeError as exc:
        raise LogError(f"cannot encode the log: {exc}") from None
    made.sort(key=lambda m: (m.packet.last_stamp_ns, spec_of(m.packet.stream).priority))
    for m in made:
        refused = _refusal(m, prefix)
        if refused is not None:
            raise LogError(refused)
    return [m.packet for m in made]
