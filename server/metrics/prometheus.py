"""Prometheus text exposition (format 0.0.4) of metric families the runtime hands over.

The runtime's ``metrics()`` returns :class:`MetricFamily` objects; this module only checks names
and renders text, so the API needs no metrics library. Example output::

    # HELP slipfleet_ingest_packets_total Packets per vehicle and outcome.
    # TYPE slipfleet_ingest_packets_total counter
    slipfleet_ingest_packets_total{vehicle="t1",reason="accepted"} 1200
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

__all__ = ["CONTENT_TYPE", "MetricFamily", "Sample", "render"]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

_NAME = re.compile(r"[a-zA-Z_:][a-zA-Z0-9_:]*")
_LABEL = re.compile(r"[a-zA-Z_][a-zA-Z0-9_]*")

MetricType = Literal["counter", "gauge", "untyped"]


@dataclass(frozen=True, slots=True)
class Sample:
    """One value of a family, with its labels (and an optional name suffix such as ``_total``)."""

    value: float
    labels: Mapping[str, str] = field(default_factory=dict)
    suffix: str = ""


@dataclass(frozen=True, slots=True)
class MetricFamily:
    """A named metric with help text, type and samples."""

    name: str
    type: MetricType
    help: str
    samples: tuple[Sample, ...] | list[Sample] = ()

    def __post_init__(self) -> None:
        if not _NAME.fullmatch(self.name):
            raise ValueError(f"invalid metric name {self.name!r}")
        for s in self.samples:
            if s.suffix and not _NAME.fullmatch(self.name + s.suffix):
                raise ValueError(f"invalid metric suffix {s.suffix!r}")
            for key in s.labels:
                if not _LABEL.fullmatch(key) or key.startswith("__"):
                    raise ValueError(f"invalid label name {key!r} in {self.name}")


def _escape_label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _escape_help(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n")


def _format_value(value: float) -> str:
    v = float(value)
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    if v.is_integer() and abs(v) < 2**53:
        return str(int(v))
    return repr(v)


def render(families: Iterable[MetricFamily]) -> str:
    """Text exposition of ``families`` (one ``# HELP``/``# TYPE`` block each, names unique)."""
    lines: list[str] = []
    seen: set[str] = set()
    for fam in families:
        if fam.name in seen:
            raise ValueError(f"metric family {fam.name!r} given twice")
        seen.add(fam.name)
        lines.append(f"# HELP {fam.name} {_escape_help(fam.help)}")
        lines.append(f"# TYPE {fam.name} {fam.type}")
        for s in fam.samples:
            if s.labels:
                inner = ",".join(f'{k}="{_escape_label(str(v))}"' for k, v in s.labels.items())
                lines.append(f"{fam.name}{s.suffix}{{{inner}}} {_format_value(s.value)}")
            else:
                lines.append(f"{fam.name}{s.suffix} {_format_value(s.value)}")
    return "\n".join(lines) + "\n" if lines else ""
