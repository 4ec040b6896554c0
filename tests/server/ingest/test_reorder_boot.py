"""Reorder buffer: a sender's boot id starts its sequence tracking afresh (``Packet.boot``)."""

from __future__ import annotations

import dataclasses

from server.ingest.reorder import BOOTS_KEPT, ReorderBuffer, Verdict
from server.protocol import Packet, Stream
from tests.server.ingest.test_reorder import MS, T0, gnss_packet, imu_packet

A, B = 7_000_000_000_000_000_001, 42


def booted(packet: Packet, boot: int | None) -> Packet:
    return dataclasses.replace(packet, boot=boot)


def drive(buf: ReorderBuffer, boot: int | None, start_ms: int, n: int) -> list[Verdict]:
    """IMU and GNSS packets numbered from 0 under ``boot``, every 100 ms from ``start_ms``."""
    verdicts = []
    for k in range(n):
        verdicts.append(buf.offer(booted(imu_packet(k, start_ms + 100 * k), boot), 0).verdict)
        verdicts.append(buf.offer(booted(gnss_packet(k, start_ms + 100 * k + 5), boot), 0).verdict)
    return verdicts


def test_a_new_boot_restarts_every_streams_numbers_counted_once() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    assert set(drive(buf, A, 0, 20)) == {Verdict.ACCEPTED}
    first = buf.offer(booted(imu_packet(0, 2000), B), 0)
    assert first.verdict is Verdict.ACCEPTED and first.seq_restart and first.lost_delta == 0
    gnss = buf.offer(booted(gnss_packet(0, 2005), B), 0)  # the other stream: the same restart
    assert gnss.verdict is Verdict.ACCEPTED and not gnss.seq_restart and gnss.lost_delta == 0
    nxt = buf.offer(booted(imu_packet(1, 2100), B), 0)
    assert nxt.verdict is Verdict.ACCEPTED and not nxt.seq_restart and nxt.lost_delta == 0
    assert buf.boot == B and buf.seq_highest() == {"imu": 1, "gnss": 0}


def test_the_same_boot_keeps_duplicates_and_gaps() -> None:
    buf = ReorderBuffer(lateness_ns=1000 * MS)
    assert buf.offer(booted(imu_packet(0, 0), A), 0).verdict is Verdict.ACCEPTED
    assert buf.offer(booted(imu_packet(3, 30), A), 0).lost_delta == 2
    assert buf.offer(booted(imu_packet(0, 0), A), 0).verdict is Verdict.DUPLICATE


def test_without_a_boot_numbers_from_0_again_are_duplicates_as_before() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    drive(buf, None, 0, 20)
    assert set(drive(buf, None, 2000, 5)) == {Verdict.DUPLICATE}
    # packets without a boot after one with it are tracked under the boot last seen
    drive(buf, A, 3000, 20)
    assert set(drive(buf, None, 5000, 5)) == {Verdict.DUPLICATE}


def test_the_first_boot_after_packets_without_one_restarts() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    drive(buf, None, 0, 20)
    offer = buf.offer(booted(imu_packet(0, 2000), A), 0)
    assert offer.verdict is Verdict.ACCEPTED and offer.seq_restart
    fresh = ReorderBuffer(lateness_ns=100 * MS)
    assert not fresh.offer(booted(imu_packet(0, 0), A), 0).seq_restart  # nothing to restart


def test_the_old_boot_after_the_new_one_is_duplicate_or_late() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    drive(buf, A, 0, 20)
    drive(buf, B, 2000, 20)
    buf.release(0)
    # a replay of the old boot's packets: still duplicates of what was seen under it
    assert buf.offer(booted(imu_packet(5, 500), A), 0).verdict is Verdict.DUPLICATE
    # one never seen before, sent before the reboot: behind the vehicle's time line now
    offer = buf.offer(booted(imu_packet(20, 1995), A), 0)
    assert offer.verdict is Verdict.LATE and not offer.seq_restart and offer.lost_delta == 0
    # the new boot goes on where it was, no restart counted on the way back
    back = buf.offer(booted(imu_packet(20, 4000), B), 0)
    assert back.verdict is Verdict.ACCEPTED and not back.seq_restart and back.lost_delta == 0
    assert buf.offer(booted(imu_packet(19, 3900), B), 0).verdict is Verdict.DUPLICATE


def test_a_boot_older_than_the_kept_ones_is_a_new_one() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    boots = list(range(1, BOOTS_KEPT + 2))
    for j, boot in enumerate(boots):
        drive(buf, boot, 3000 * j, 5)
    offer = buf.offer(booted(imu_packet(0, 3000 * len(boots)), boots[0]), 0)
    assert offer.verdict is Verdict.ACCEPTED and offer.seq_restart
    # the boot before it is still kept: its numbers go on without a restart or a loss
    offer = buf.offer(booted(imu_packet(5, 3000 * len(boots) + 100), boots[-1]), 0)
    assert offer.verdict is Verdict.ACCEPTED and not offer.seq_restart and offer.lost_delta == 0


def test_the_watermarks_follow_the_new_boot() -> None:
    """Every stream's run of consecutive numbers starts afresh at its first packet of the new
    boot: the release follows the new boot's packets, not the fixed window."""
    buf = ReorderBuffer(
        lateness_ns=300 * MS, idle_ns=10**18, watermarks=True, streams=(Stream.IMU,)
    )
    for k in range(12):
        buf.offer(booted(imu_packet(k, 100 * k), A), 0)
    buf.release(0)
    buf.offer(booted(imu_packet(0, 1200), B), 0)
    buf.offer(booted(imu_packet(1, 1300), B), 0)
    assert buf.release(0)[1] == T0 + 1309 * MS


def test_resume_keeps_the_boot() -> None:
    buf = ReorderBuffer(lateness_ns=100 * MS)
    buf.resume_seq({"imu": 100}, boot=A)
    assert buf.boot == A
    assert buf.offer(booted(imu_packet(100, 0), A), 0).verdict is Verdict.DUPLICATE
    assert buf.offer(booted(imu_packet(103, 30), A), 0).lost_delta == 2
    other = ReorderBuffer(lateness_ns=100 * MS)
    other.resume_seq({"imu": 100}, boot=A)
    offer = other.offer(booted(imu_packet(0, 0), B), 0)  # rebooted while the server was down
    assert offer.verdict is Verdict.ACCEPTED and offer.seq_restart and offer.lost_delta == 0
