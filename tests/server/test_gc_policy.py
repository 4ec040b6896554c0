"""The collector settings a server or worker process takes once it has started."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from server.gc_policy import settle


@pytest.fixture
def restore_gc() -> Iterator[None]:
    before = gc.get_threshold()
    yield
    gc.unfreeze()
    gc.set_threshold(*before)


@pytest.mark.usefixtures("restore_gc")
def test_settle_freezes_startup_objects_and_raises_the_young_threshold() -> None:
    _, gen1, gen2 = gc.get_threshold()
    gc.unfreeze()
    settle(40_000)
    assert gc.get_threshold() == (40_000, gen1, gen2)
    assert gc.get_freeze_count() > 1000  # this interpreter's modules, functions, classes …


@pytest.mark.usefixtures("restore_gc")
def test_settle_zero_leaves_the_collector_alone() -> None:
    gc.unfreeze()
    before = gc.get_threshold()
    settle(0)
    assert gc.get_threshold() == before
    assert gc.get_freeze_count() == 0


@pytest.mark.usefixtures("restore_gc")
def test_cycles_made_after_settling_are_still_collected() -> None:
    gc.unfreeze()
    settle(40_000)

    class Node:
        other: object = None

    a, b = Node(), Node()
    a.other, b.other = b, a
    del a, b
    assert gc.collect() >= 2
