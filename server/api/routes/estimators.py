"""``/estimators``: every estimator the server knows, described by its spec.

The dashboard reads this once and draws charts, tiles and flags from it; a client learns which
``estimator`` values the estimate routes take and what each row holds (fields with units, flags,
slip and speed channels, position).
"""

from __future__ import annotations

from fastapi import APIRouter

from estimator.catalog import SPECS
from server.api.models import EstimatorSpecPublic, EstimatorsPublic

__all__ = ["router"]

router = APIRouter(prefix="/estimators", tags=["estimators"])


@router.get(
    "",
    response_model=EstimatorsPublic,
    summary="Every estimator's spec",
    description="Each estimator's name, inputs, output fields (unit, label, description), flag "
    "bits and channels (slip, speed, motion, position, charts), by name.",
)
def list_estimators() -> EstimatorsPublic:
    specs = [EstimatorSpecPublic.model_validate(SPECS[name].to_dict()) for name in sorted(SPECS)]
    return EstimatorsPublic(data=specs, count=len(specs))
