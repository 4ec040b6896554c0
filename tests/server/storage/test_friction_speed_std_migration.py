"""The migration that appends the friction row's speed 1-sigma: rows stored before it (SQLite:
final and still staged) read back with every old field bit for bit and no 1-sigma (NaN), and
the table then takes rows with one, on both backends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.friction_spec import FRICTION_SPEC
from estimator.spec import EstimatorSpec
from server.storage.migrations import FRICTION_FIELDS_V16, FRICTION_FIELDS_V19
from tests.server.storage.appended_fields import (
    VEHICLE,
    appended_names,
    assert_new_rows_taken,
    assert_old_rows_read_back,
    migrated,
    migration_version,
    spec_before,
)
from tests.server.storage.conftest import Backend

_ADDED = appended_names(FRICTION_FIELDS_V16, FRICTION_FIELDS_V19)
_VERSION = migration_version("friction rows carry the speed's")


def spec_before_speed_std() -> EstimatorSpec:
    """The friction spec as it was before the speed's 1-sigma: version 16's fields, and the
    speed channel without it."""
    return spec_before(
        FRICTION_SPEC,
        FRICTION_FIELDS_V16,
        _ADDED,
        speeds=tuple(dataclasses.replace(c, std_field=None) for c in FRICTION_SPEC.speeds),
    )


def test_the_migration_appends_the_specs_speed_std() -> None:
    assert _ADDED == ("vx_std_mps",)
    assert FRICTION_SPEC.field_names[-1] == "vx_std_mps"
    assert FRICTION_SPEC.speeds[0].std_field == "vx_std_mps"


def test_rows_stored_before_read_back_without_a_speed_std(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = spec_before_speed_std()
    with migrated(backend, FRICTION_SPEC, before, _VERSION, "wheeled_4wd_steered", monkeypatch) as (
        new,
        want,
    ):
        assert_old_rows_read_back(new, FRICTION_SPEC, want, _ADDED)
        assert_new_rows_taken(new, FRICTION_SPEC, _ADDED)
        got = new.query_series(VEHICLE, 0, 2**62, estimator="friction", fields=list(_ADDED))
        assert got.size == 60 and np.isfinite(got["vx_std_mps"][-10:]).all()
