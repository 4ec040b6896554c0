"""EstimateBatch: several vehicles' rows joined once, read as (vehicle_id, rows) pairs."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.catalog import spec_of
from estimator.types import ESTIMATE_DTYPE, EstimateBatch, concat_estimates, empty_estimates

MDSF = spec_of("mdsf")
REF = spec_of("reference_speed")


def _rows(*stamps: int) -> np.ndarray:
    rows = empty_estimates(len(stamps))
    rows["stamp_ns"] = stamps
    return rows


def test_of_joins_the_non_empty_parts_in_order() -> None:
    batch = EstimateBatch.of([("a", _rows(1, 2)), ("b", _rows()), ("c", _rows(3))], MDSF)
    assert batch.ids == ["a", "c"]
    assert batch.counts == [2, 1]
    assert batch.rows.dtype == ESTIMATE_DTYPE
    assert batch.rows["stamp_ns"].tolist() == [1, 2, 3]
    assert [(vid, rows["stamp_ns"].tolist()) for vid, rows in batch] == [("a", [1, 2]), ("c", [3])]
    rows, key = batch.grouped(np.array([7, 3]))
    assert rows is batch.rows and key.tolist() == [7, 7, 3]


def test_items_are_views_of_the_joined_rows() -> None:
    batch = EstimateBatch.of([("a", _rows(1, 2)), ("c", _rows(3))], MDSF)
    _, rows = batch[-1]
    assert np.shares_memory(rows, batch.rows)
    assert batch[0:2][1][0] == "c"
    with pytest.raises(IndexError):
        batch[2]


def test_of_a_batch_is_that_batch_and_an_empty_one_is_falsy() -> None:
    batch = EstimateBatch.of([("a", _rows(1))], MDSF)
    assert EstimateBatch.of(batch, MDSF) is batch
    assert batch.estimator == "mdsf"
    empty = EstimateBatch.of([("a", _rows())], MDSF)
    assert not empty and empty.rows.shape == (0,)


def test_counts_that_do_not_add_up_are_refused() -> None:
    with pytest.raises(ValueError, match="disagree"):
        EstimateBatch(["a", "b"], [1, 1], _rows(1), MDSF)


def test_a_vehicle_named_twice_is_grouped_in_time_order() -> None:
    batch = EstimateBatch.of([("a", _rows(1, 2)), ("b", _rows(5)), ("a", _rows(3))], MDSF)
    rows, key = batch.grouped(np.array([0, 1, 0]))
    assert key.tolist() == [0, 0, 0, 1]
    assert rows["stamp_ns"].tolist() == [1, 2, 3, 5]


def test_a_batch_holds_one_estimators_rows_of_any_spec() -> None:
    ref = REF.empty_rows(2)
    ref["stamp_ns"] = [4, 5]
    batch = EstimateBatch.of([("a", ref), ("b", ref[:1])], REF)
    assert batch.estimator == "reference_speed" and batch.rows.dtype == REF.dtype
    assert batch.rows["stamp_ns"].tolist() == [4, 5, 4]
    with pytest.raises(TypeError, match="must have its dtype"):
        EstimateBatch.of([("a", ref), ("b", _rows(1))], REF)
    with pytest.raises(TypeError, match="must have its dtype"):
        EstimateBatch(["a"], [2], ref, MDSF)


def test_rows_of_two_estimators_never_join() -> None:
    with pytest.raises(TypeError, match="different dtypes"):
        concat_estimates([_rows(1), REF.empty_rows(1)])
