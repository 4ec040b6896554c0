"""Every estimator's spec by name: what the server reads before it builds any estimator.

Adding an estimator: declare its :class:`estimator.spec.EstimatorSpec` beside it and list it here;
its factory goes in the server's registry (``server.estimation.registry``).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from estimator.friction_spec import FRICTION_SPEC
from estimator.mdsf_spec import MDSF_SPEC
from estimator.reference_speed_spec import REFERENCE_SPEED_SPEC
from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC

__all__ = ["SPECS", "spec_of"]

SPECS: Mapping[str, EstimatorSpec] = MappingProxyType(
    {s.name: s for s in (MDSF_SPEC, REFERENCE_SPEED_SPEC, FRICTION_SPEC, TRACKED_SPEC)}
)


def spec_of(name: str) -> EstimatorSpec:
    """The spec named ``name`` (``KeyError`` listing the known ones)."""
    try:
        return SPECS[name]
    except KeyError:
        raise KeyError(f"unknown estimator {name!r}; known: {sorted(SPECS)}") from None
