"""The viewer's garbage-collector measures: full collections counted and timed, and the start-up's
objects frozen out of them."""

from __future__ import annotations

import gc

from lidarloc.app.viewer.collector import FullCollections, freeze_startup


def test_full_collections_are_counted_and_timed_and_take_starts_again():
    timer = FullCollections()
    try:
        timer.take()
        gc.collect(0)  # a young generation's collection is not a full one
        assert timer.take() == {"count": 0, "longest_ms": 0.0}
        gc.collect()
        gc.collect()
        first = timer.take()
        assert first["count"] == 2 and first["longest_ms"] >= 0.0
        assert timer.take()["count"] == 0
    finally:
        timer.close()
    gc.collect()
    assert timer.take()["count"] == 0  # unhooked
    timer.close()  # twice is harmless


def test_frozen_start_up_objects_leave_the_full_collection_and_new_garbage_is_still_collected():
    long_lived = [[i] for i in range(400_000)]  # the start-up's modules and map, as many objects
    timer = FullCollections()
    try:
        gc.collect()
        timer.take()
        for _ in range(3):
            gc.collect()
        before = timer.take()["longest_ms"]
        frozen = freeze_startup()
        assert frozen >= len(long_lived)
        for _ in range(3):
            gc.collect()
        after = timer.take()["longest_ms"]
        # the walk over 400 k objects is gone: a tenth of the time at most (measured ~1/100)
        assert after < before / 10, (before, after)

        class Node:
            pass

        cycle = Node()
        cycle.me = cycle  # garbage only a collection frees, made after the freeze
        del cycle
        assert gc.collect() >= 1
    finally:
        timer.close()
        gc.unfreeze()  # the rest of the test session collects as before
    assert gc.get_freeze_count() == 0
