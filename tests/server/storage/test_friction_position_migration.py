"""The migration that appends the friction row's position: rows stored before it (SQLite: final
and still staged) read back with every old field bit for bit and no position (NaN), and the
table then takes rows with one, on both backends."""

from __future__ import annotations

import pytest

from estimator.friction_spec import FRICTION_SPEC
from estimator.spec import EstimatorSpec
from server.storage.migrations import (
    FRICTION_FIELDS_V12,
    FRICTION_FIELDS_V16,
)
from tests.server.storage.appended_fields import (
    appended_names,
    assert_new_rows_taken,
    assert_old_rows_read_back,
    migrated,
    migration_version,
    spec_before,
)
from tests.server.storage.conftest import Backend
from tests.server.storage.test_friction_speed_std_migration import spec_before_speed_std

_ADDED = appended_names(FRICTION_FIELDS_V12, FRICTION_FIELDS_V16)
_VERSION = migration_version("the friction estimator's position")


def _spec_before() -> EstimatorSpec:
    """The friction spec as it was before the position: version 12's fields, no position (and
    no speed 1-sigma, which came later)."""
    return spec_before(
        spec_before_speed_std(),
        FRICTION_FIELDS_V12,
        _ADDED,
        position=None,
        degraded_flags=("HELD",),
    )


def test_rows_stored_before_read_back_without_a_position(
    backend: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = _spec_before()
    with migrated(backend, FRICTION_SPEC, before, _VERSION, "wheeled_4wd_steered", monkeypatch) as (
        new,
        want,
    ):
        assert_old_rows_read_back(new, FRICTION_SPEC, want, _ADDED)
        assert_new_rows_taken(new, FRICTION_SPEC, _ADDED)
