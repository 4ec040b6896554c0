"""The migration that appends the tracked row's GNSS receiver clock (its offset and 1-sigma, the
second online calibration): rows stored before it (SQLite: final and still staged) read back with
every old field bit for bit and no clock (NaN), and the table then takes rows with one, on both
backends; a restart restores the clock of a row that has one and no gyro measurement."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.spec import EstimatorSpec
from estimator.tracked_spec import TRACKED_SPEC
from server.estimation.calibration import stored_calibrations
from server.storage.migrations import TRACKED_FIELDS_V18, TRACKED_FIELDS_V20
from tests.server.storage.appended_fields import (
    VEHICLE,
    appended_names,
    assert_new_rows_taken,
    assert_old_rows_read_back,
    migrated,
    migration_version,
    spec_before,
)
from tests.server.storage.conftest import Backend, batch_of, make_spec_rows

_ADDED = appended_names(TRACKED_FIELDS_V18, TRACKED_FIELDS_V20)
_VERSION = migration_version("tracked rows carry the GNSS")


def spec_before_clock() -> EstimatorSpec:
    """The tracked spec as it was before the clock: version 18's fields and the gyro's
    calibration channel alone."""
    return spec_before(
        TRACKED_SPEC,
        TRACKED_FIELDS_V18,
        _ADDED,
        calibrations=tuple(c for c in TRACKED_SPEC.calibrations if c.field not in _ADDED),
    )


def test_the_migration_appends_the_specs_clock_fields() -> None:
    assert _ADDED == ("gnss_clock_offset_s", "gnss_clock_offset_std_s")
    assert TRACKED_SPEC.field_names[-len(_ADDED) :] == _ADDED


def test_rows_stored_before_read_back_without_a_clock(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = spec_before_clock()
    with migrated(backend, TRACKED_SPEC, before, _VERSION, "tracked", monkeypatch) as (new, want):
        assert_old_rows_read_back(new, TRACKED_SPEC, want, _ADDED)
        # the old rows' gyro measurement is restored without a clock
        stored = stored_calibrations(new)[(VEHICLE, "tracked")]
        assert set(stored) == {"gyro_arw_deg_rt_h", "gyro_arw_std_deg_rt_h"}
        assert_new_rows_taken(new, TRACKED_SPEC, _ADDED)
        got = new.query_series(VEHICLE, 0, 2**62, estimator="tracked", fields=list(_ADDED))
        assert np.isnan(got["gnss_clock_offset_s"][:50]).all()
        assert np.isfinite(got["gnss_clock_offset_s"][-10:]).all()


def test_a_clock_without_a_gyro_measurement_is_stored_for_a_restart(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A crawler that has not stood yet has no gyro measurement (NaN) but a learnt clock: the
    clock alone is what a restart restores."""
    before = spec_before_clock()
    with migrated(backend, TRACKED_SPEC, before, _VERSION, "tracked", monkeypatch) as (new, _):
        rows = make_spec_rows(TRACKED_SPEC, 5, seed=9)
        rows["stamp_ns"] += 10**15
        rows["gyro_arw_deg_rt_h"] = np.nan
        rows["gyro_arw_std_deg_rt_h"] = np.nan
        rows["gnss_clock_offset_s"][-1] = 0.0625
        rows["gnss_clock_offset_std_s"][-1] = 0.004
        new.write_estimates(batch_of(TRACKED_SPEC, {VEHICLE: rows}))
        stored = stored_calibrations(new)[(VEHICLE, "tracked")]
        assert stored == {"gnss_clock_offset_s": 0.0625, "gnss_clock_offset_std_s": 0.004}
