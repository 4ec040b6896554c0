"""The migration that appends the tracked row's attitude (pitch, roll and their 1-sigma): rows
stored before it (SQLite: final and still staged) read back with every old field bit for bit and
no attitude (NaN), and the table then takes rows with one, on both backends."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC
from server.storage.migrations import TRACKED_FIELDS_V17, TRACKED_FIELDS_V18
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
from tests.server.storage.test_tracked_clock_migration import spec_before_clock

_ADDED = appended_names(TRACKED_FIELDS_V17, TRACKED_FIELDS_V18)
_VERSION = migration_version("tracked rows carry the hull's")


def spec_before_attitude() -> EstimatorSpec:
    """The tracked spec as it was before the attitude: version 17's fields, and no channel,
    chart or alert reading the pitch or roll."""
    assert TRACKED_SPEC.position is not None
    return spec_before(
        spec_before_clock(),
        TRACKED_FIELDS_V17,
        _ADDED,
        position=dataclasses.replace(TRACKED_SPEC.position, pitch_field=None, roll_field=None),
        charts=tuple(c for c in TRACKED_SPEC.charts if not set(c.fields) & set(_ADDED)),
        alerts=tuple(a for a in TRACKED_SPEC.alerts if a.field not in _ADDED),
    )


def test_the_migration_appends_the_specs_attitude_fields() -> None:
    assert _ADDED == ("pitch_rad", "pitch_std_rad", "roll_rad", "roll_std_rad")
    assert tuple(f for f, _ in TRACKED_FIELDS_V18[-len(_ADDED) :]) == _ADDED
    assert spec_before_clock().field_names[-len(_ADDED) :] == _ADDED


def test_rows_stored_before_read_back_without_an_attitude(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = spec_before_attitude()
    with migrated(backend, TRACKED_SPEC, before, _VERSION, "tracked", monkeypatch) as (new, want):
        assert_old_rows_read_back(new, TRACKED_SPEC, want, _ADDED)
        assert_new_rows_taken(new, TRACKED_SPEC, _ADDED)
        got = new.query_series(VEHICLE, 0, 2**62, estimator="tracked", fields=list(_ADDED))
        assert got.size == 60 and np.isfinite(got["roll_rad"][-10:]).all()
