"""The daemon's log names a full garbage collection that held it (core/heap.py)."""

from __future__ import annotations

import gc
import logging
import re
from collections.abc import Iterator

import pytest

from pseudotwin.core import heap


@pytest.fixture
def watch_only(request: pytest.FixtureRequest) -> Iterator[None]:
    """The module's watch alone in gc.callbacks, with the test's threshold; restored after.
    Automatic collections are off: only the test's own ones count."""
    before = list(gc.callbacks)
    gc.callbacks[:] = [cb for cb in before if not isinstance(cb, heap._FullCollectionWatch)]
    heap.watch_full_collections(request.param)
    gc.disable()
    gc.unfreeze()  # an in-process backfill of an earlier test may have frozen some
    try:
        yield
    finally:
        gc.enable()
        gc.callbacks[:] = before
        gc.unfreeze()  # what the test froze goes back to the collector


@pytest.mark.parametrize("watch_only", [0.0], indirect=True)  # every full collection is long
def test_a_long_full_collection_is_logged_later_and_a_young_one_is_not(
        watch_only: None, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="pseudotwin.core.heap"):
        gc.collect(0)
        heap.log_long_collections()
        assert not caplog.records
        gc.collect()  # generation 2
        assert not caplog.records  # not inside the collection: by the main loop's call
        heap.log_long_collections()
        heap.log_long_collections()  # logged once
    assert len(caplog.records) == 1
    # the line scripts/bench_daemon.py counts, as the CLI's log format writes it
    line = logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s").format(
        caplog.records[0])
    found = re.findall(heap.LONG_PAUSE_PATTERN, line)
    assert len(found) == 1 and int(found[0][1]) > 0


@pytest.mark.parametrize("watch_only", [3600.0], indirect=True)
def test_a_short_full_collection_is_not_logged(
        watch_only: None, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="pseudotwin.core.heap"):
        gc.collect()
        heap.log_long_collections()
    assert not caplog.records


@pytest.mark.parametrize("watch_only", [0.1], indirect=True)
def test_the_watch_is_installed_once(watch_only: None) -> None:
    heap.watch_full_collections()
    assert sum(isinstance(cb, heap._FullCollectionWatch) for cb in gc.callbacks) == 1


@pytest.mark.parametrize("watch_only", [0.0], indirect=True)
def test_what_a_long_full_collection_left_is_frozen(watch_only: None) -> None:
    survivor = [object()]
    gc.collect()
    assert gc.is_tracked(survivor) and gc.get_freeze_count() == 0
    heap.log_long_collections()
    assert gc.get_freeze_count() > 0
    assert not any(o is survivor for o in gc.get_objects(generation=2))  # not traversed


@pytest.mark.parametrize("watch_only", [3600.0], indirect=True)
def test_a_short_full_collection_freezes_nothing(watch_only: None) -> None:
    gc.collect()
    heap.log_long_collections()
    assert gc.get_freeze_count() == 0


@pytest.mark.parametrize("watch_only", [3600.0], indirect=True)  # no collection is long
def test_a_thaw_hands_frozen_objects_back_and_the_next_full_collection_refreezes(
        watch_only: None, caplog: pytest.LogCaptureFixture) -> None:
    watch = heap._watch()
    assert watch is not None
    gc.freeze()  # as freeze_long_lived does at startup
    frozen = gc.get_freeze_count()
    heap.log_long_collections(now=watch.thawed_at + heap.THAW_S - 1.0)
    assert frozen > 0 and gc.get_freeze_count() == frozen  # not yet
    with caplog.at_level(logging.INFO, logger="pseudotwin.core.heap"):
        heap.log_long_collections(now=watch.thawed_at + heap.THAW_S)
    assert gc.get_freeze_count() == 0
    assert any(f"{frozen} frozen objects handed back" in r.getMessage() for r in caplog.records)
    heap.log_long_collections(now=watch.thawed_at)
    assert gc.get_freeze_count() == 0  # no full collection has passed over them yet
    gc.collect()  # a short one: not logged, but it follows the thaw
    heap.log_long_collections(now=watch.thawed_at)
    assert gc.get_freeze_count() > 0


@pytest.mark.parametrize("watch_only", [0.0], indirect=True)
def test_a_long_collection_from_before_a_thaw_does_not_refreeze_at_once(
        watch_only: None) -> None:
    watch = heap._watch()
    assert watch is not None
    gc.collect()  # long, still to be logged
    heap.log_long_collections(now=watch.thawed_at + heap.THAW_S)  # the thaw comes first
    assert gc.get_freeze_count() == 0
    gc.collect()
    heap.log_long_collections(now=watch.thawed_at)
    assert gc.get_freeze_count() > 0
