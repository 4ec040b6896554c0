"""A burst's accepted packets counted at once equal the same packets counted one by one."""

from __future__ import annotations

from server.ingest.counters import IngestCounters


def test_accepted_many_equals_accepted_one_by_one() -> None:
    one_by_one, at_once = IngestCounters(), IngestCounters()
    for vid, lost in (("a", 0), ("a", 2), ("b", 0), ("a", -1)):
        one_by_one.accepted(vid, lost)
    one_by_one.late("b")
    at_once.late("b")
    at_once.accepted_many({"a": (3, 1), "b": (1, 0)})
    assert at_once.snapshot() == one_by_one.snapshot()
    assert at_once.snapshot()["a"]["received"] == 3


def test_accepted_many_of_nothing_adds_no_vehicle() -> None:
    c = IngestCounters()
    c.accepted_many({})
    assert c.snapshot() == {}
