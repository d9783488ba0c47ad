"""The daemon's log names a full garbage collection that paused it (core/heap.py)."""

from __future__ import annotations

import gc
import logging

import pytest

from pseudotwin.core import heap


def test_a_long_full_collection_is_logged_and_a_young_one_is_not(
        caplog: pytest.LogCaptureFixture) -> None:
    watch = heap._FullCollectionWatch(threshold_s=0.0)  # every full collection is "long"
    gc.callbacks.append(watch)
    try:
        with caplog.at_level(logging.WARNING, logger="pseudotwin.core.heap"):
            gc.collect(0)
            assert not caplog.records
            gc.collect()  # generation 2
    finally:
        gc.callbacks.remove(watch)
    assert len(caplog.records) == 1
    assert "full garbage collection paused every thread" in caplog.records[0].getMessage()


def test_a_short_full_collection_is_not_logged(caplog: pytest.LogCaptureFixture) -> None:
    watch = heap._FullCollectionWatch(threshold_s=3600.0)
    gc.callbacks.append(watch)
    try:
        with caplog.at_level(logging.WARNING, logger="pseudotwin.core.heap"):
            gc.collect()
    finally:
        gc.callbacks.remove(watch)
    assert not caplog.records


def test_the_watch_is_installed_once() -> None:
    before = list(gc.callbacks)
    try:
        heap.watch_full_collections()
        heap.watch_full_collections()
        added = [cb for cb in gc.callbacks if cb not in before]
        assert len(added) <= 1
        assert sum(isinstance(cb, heap._FullCollectionWatch) for cb in gc.callbacks) == 1
    finally:
        gc.callbacks[:] = before
