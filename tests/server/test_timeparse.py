"""ISO 8601 / epoch-nanosecond query times."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.timeparse import INT64_MAX, TimeParseError, format_ns, parse_time_ns

T0 = 1_704_164_645_000_000_000  # 2024-01-02T03:04:05Z


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("2024-01-02T03:04:05Z", T0),
        ("2024-01-02T03:04:05+00:00", T0),
        ("2024-01-02T05:04:05+02:00", T0),
        ("2024-01-01T22:04:05-05:00", T0),
        ("2024-01-02T03:04:05.5Z", T0 + 500_000_000),
        ("2024-01-02T03:04:05.123456789Z", T0 + 123_456_789),
        ("2024-01-02T03:04:05.1234567891Z", T0 + 123_456_789),  # beyond ns: truncated
        ("2024-01-02T03:04:05,25Z", T0 + 250_000_000),
        ("2024-01-02 03:04:05Z", T0),
        ("20240102T030405.000000001Z", T0 + 1),
        ("1704164645000000000", T0),
        (" 0 ", 0),
    ],
)
def test_accepted(text: str, expected: int) -> None:
    assert parse_time_ns(text) == expected


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("2024-01-02T03:04:05", "without a UTC offset"),
        ("2024-01-02", "without a UTC offset"),
        ("", "empty"),
        ("yesterday", "not an ISO 8601"),
        ("-5", "not an ISO 8601"),
        ("1.5e18", "not an ISO 8601"),
        (str(INT64_MAX + 1), "out of range"),
        ("1969-12-31T23:59:59Z", "before 1970"),
        ("9" * 80, "too long"),
    ],
)
def test_refused_with_reason(text: str, reason: str) -> None:
    with pytest.raises(TimeParseError, match=reason):
        parse_time_ns(text)


@given(st.integers(min_value=0, max_value=253_402_300_799_999_999_999 // 1000))
def test_format_round_trips(stamp_ns: int) -> None:
    stamp_ns = min(stamp_ns, INT64_MAX)
    text = format_ns(stamp_ns)
    assert text.endswith("Z")
    assert parse_time_ns(text) == stamp_ns
