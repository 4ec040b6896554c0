"""Parse query times into integer nanoseconds since the Unix epoch (UTC).

Three spellings are accepted:

* **Epoch nanoseconds**: a string of decimal digits, e.g. ``1700000000000000000``. Any string
  made only of digits is read this way (so the ISO *basic* date ``20240102`` is not a date here).
* **ISO 8601 with a UTC offset**: ``2024-05-01T12:00:00Z``, ``2024-05-01T14:00:00.123456789+02:00``.
  Fractions of a second keep up to 9 digits (nanoseconds); further digits are truncated.
* **Relative to now**: ``now``, or ``now-`` a number and a unit (``s``, ``m``, ``h``, ``d``),
  e.g. ``now-15m``, ``now-1.5h``, ``now-7d``: the caller passes its clock as ``now_ns`` (the
  API passes the server's wall clock when the request is read). Only the past: a report
  reaches no further than now.

A time without an offset (``2024-05-01T12:00:00``, ``2024-05-01``) is **rejected**, not taken as
UTC: the server cannot know which clock the caller meant, and guessing shifts data by hours.
"""

from __future__ import annotations

import re
from datetime import UTC, datetime

__all__ = ["INT64_MAX", "TimeParseError", "format_ns", "parse_time_ns"]

INT64_MAX = 2**63 - 1
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_DIGITS = re.compile(r"[0-9]+")
# Seconds with a decimal fraction right after the date/time separator: hh:mm:ss.fff or hhmmss,fff.
_SECONDS_FRACTION = re.compile(r"([0-9]{2}:?[0-9]{2}:?[0-9]{2})[.,]([0-9]+)")
_MAX_LEN = 64
_RELATIVE = re.compile(r"now(?:-([0-9]+(?:\.[0-9]+)?)([smhd]))?")
_UNIT_S = {"s": 1, "m": 60, "h": 3_600, "d": 86_400}


class TimeParseError(ValueError):
    """The text is not epoch nanoseconds, an ISO 8601 time with a UTC offset or a time
    relative to now (or is one that no clock was given for)."""


def parse_time_ns(text: str, now_ns: int | None = None) -> int:
    """Return the time ``text`` names as int nanoseconds since the epoch, UTC.

    ``now_ns`` is the clock relative times (``now``, ``now-15m``) count from; without it they
    are refused.

    Raises
    ------
    TimeParseError
        With a reason a client can act on.
    """
    value = text.strip()
    if not value:
        raise TimeParseError("empty time")
    if len(value) > _MAX_LEN:
        raise TimeParseError("time text too long")
    if _DIGITS.fullmatch(value):
        ns = int(value)
        if ns > INT64_MAX:
            raise TimeParseError(f"epoch nanoseconds out of range (max {INT64_MAX})")
        return ns
    if value.lower().startswith("now"):
        return _parse_relative(value, text, now_ns)
    return _parse_iso(value)


def _parse_relative(value: str, text: str, now_ns: int | None) -> int:
    m = _RELATIVE.fullmatch(value.lower())
    if m is None:
        raise TimeParseError(
            f"not a relative time: {text!r}; write 'now' or 'now-' a number and s, m, h or d"
        )
    if now_ns is None:
        raise TimeParseError("a relative time needs a clock to count from")
    ago_ns = (
        0 if m.group(1) is None else round(float(m.group(1)) * _UNIT_S[m.group(2)] * 1_000_000_000)
    )
    ns = now_ns - ago_ns
    if ns < 0:
        raise TimeParseError(f"{text!r} lies before 1970-01-01")
    return ns


def _parse_iso(text: str) -> int:
    value = text
    # datetime.fromisoformat keeps only microseconds; take the fraction out and add it back as ns.
    sep = max(value.find("T"), value.find("t"), value.find(" "))
    frac_ns = 0
    if sep >= 0:
        m = _SECONDS_FRACTION.match(value, sep + 1)
        if m is not None:
            frac_ns = int(m.group(2)[:9].ljust(9, "0"))
            value = value[: m.end(1)] + value[m.end() :]
    try:
        dt = datetime.fromisoformat(value)
    except ValueError as exc:
        raise TimeParseError(f"not an ISO 8601 time or epoch nanoseconds: {text!r}") from exc
    if dt.tzinfo is None or dt.utcoffset() is None:
        raise TimeParseError("ISO 8601 time without a UTC offset is refused; add 'Z' or '+hh:mm'")
    delta = dt - _EPOCH
    ns = (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000
    ns += frac_ns
    if not 0 <= ns <= INT64_MAX:
        raise TimeParseError("time before 1970-01-01 or beyond the int64 nanosecond range")
    return ns


def format_ns(stamp_ns: int) -> str:
    """ISO 8601 UTC text with nanoseconds, e.g. ``2024-05-01T12:00:00.000000001Z``."""
    sec, frac = divmod(int(stamp_ns), 1_000_000_000)
    dt = datetime.fromtimestamp(sec, tz=UTC)
    return f"{dt:%Y-%m-%dT%H:%M:%S}.{frac:09d}Z"
