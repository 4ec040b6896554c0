"""The migration that appends the tracked row's online calibration (the gyro's noise measured
standing): rows stored before it (SQLite: final and still staged) read back with every old field
bit for bit and no measurement (NaN, which a restart does not restore), and the table then takes
rows with one, on both backends."""

from __future__ import annotations

import pytest

from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC
from server.estimation.calibration import stored_calibrations
from server.storage.migrations import (
    TRACKED_FIELDS_V13,
    TRACKED_FIELDS_V17,
)
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
from tests.server.storage.test_tracked_attitude_migration import spec_before_attitude

_ADDED = appended_names(TRACKED_FIELDS_V13, TRACKED_FIELDS_V17)
_VERSION = migration_version("tracked rows carry the gyro's noise")


def _spec_before() -> EstimatorSpec:
    """The tracked spec as it was before the calibration: version 13's fields, none (and no
    attitude, which came later)."""
    return spec_before(spec_before_attitude(), TRACKED_FIELDS_V13, _ADDED, calibrations=())


def test_rows_stored_before_read_back_without_a_calibration(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = _spec_before()
    with migrated(backend, TRACKED_SPEC, before, _VERSION, "tracked", monkeypatch) as (new, want):
        assert_old_rows_read_back(new, TRACKED_SPEC, want, _ADDED)
        assert stored_calibrations(new) == {}  # nothing measured: nothing to restore
        assert_new_rows_taken(new, TRACKED_SPEC, _ADDED)
        assert set(stored_calibrations(new)) == {(VEHICLE, "tracked")}
