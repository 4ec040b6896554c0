"""What ``slipfleet replay`` says about the server's counters: they are per vehicle, so while
the replayed vehicle is itself sending (a demo's ``sim-0001``), its own packets are counted
beside the replayed ones and the line must not pass them off as the recording's."""

from __future__ import annotations

from collections import Counter

from server.tooling.recording_commands import _verdict


def test_a_replay_alone_is_counted_as_the_recording() -> None:
    lines = _verdict(602, Counter(received=602, accepted=602), ["tractor-9"])
    assert lines == [
        "the server received 602 of them: 602 accepted, 0 late, 0 duplicate, 0 rejected"
    ]


def test_traffic_of_a_sending_vehicle_is_not_passed_off_as_the_recording() -> None:
    delta = Counter(received=765, accepted=163, duplicate=602)
    lines = _verdict(602, delta, ["sim-0001"])
    assert "received 765 of them" not in lines[0]
    assert "765 packets of sim-0001 meanwhile, 163 more than were replayed" in lines[0]
    assert "the vehicle is sending too" in lines[0]
    assert lines[0].endswith("163 accepted, 0 late, 602 duplicate, 0 rejected")
    assert any(line.startswith("duplicate:") and "--as NEW_ID" in line for line in lines)
