"""freeze_startup_objects: start-up objects leave the garbage collector's generations; garbage does not survive."""

import gc

import pytest

from slipest.startup_gc import freeze_startup_objects


@pytest.fixture
def unfrozen():
    yield
    gc.unfreeze()  # give the test process its generations back


def test_startup_objects_are_frozen_and_startup_garbage_is_collected(unfrozen):
    kept = [[1, 2], {"a": [3]}]  # live start-up objects: tracked by the collector until frozen
    cycle = []
    cycle.append(cycle)  # start-up garbage that only a collection frees
    collected = []
    gc.callbacks.append(lambda phase, info: phase == "stop" and collected.append(info["collected"]))
    try:
        del cycle
        assert any(o is kept for o in gc.get_objects())
        n = freeze_startup_objects()
    finally:
        gc.callbacks.pop()
    assert n > 1000  # imports alone leave thousands
    assert sum(collected) >= 1  # the garbage cycle was collected before freezing, not frozen
    # later full collections walk only what is made from now on
    assert not any(o is kept for o in gc.get_objects())
    made_later = [[4]]
    assert any(o is made_later for o in gc.get_objects())
