"""Long-lived objects out of the cyclic garbage collector's way.

A process that loads its modules and twins once and then allocates many short-lived objects
(a reading, an estimate, a row) triggers collections that traverse every object alive, the
imported numpy/scipy/pandas and the twins included. ``gc.freeze`` moves what is alive now
into a permanent generation that no collection traverses: the daemon's full collections over
a thousand twins stopped every thread for ~0.7 s, and a backfill in one process spent ~20 %
of its CPU in them (30 days of one twin: 6.0 s → 4.8–5.2 s). The backfill's worker processes
measured no gain (their work is the same, their heap smaller), so they do not freeze.

What is allocated later still gets collected, and a full collection stops every thread:
:func:`watch_full_collections` logs each one that pauses the process for longer than a
reading's latency budget can spare, so a latency spike in a daemon's log has its cause next
to it.
"""

from __future__ import annotations

import gc
import logging
import time
from typing import Any

log = logging.getLogger(__name__)

#: A full collection pausing the process for longer than this is logged [s].
LONG_PAUSE_S = 0.1


def freeze_long_lived() -> None:
    """Collect once, then exempt every object alive now from later collections. For the
    processes pseudotwin's commands own (daemon, recorder, backfill), after loading."""
    gc.collect()
    gc.freeze()


class _FullCollectionWatch:
    """A ``gc.callbacks`` entry timing generation-2 collections."""

    def __init__(self, threshold_s: float) -> None:
        self.threshold_s = threshold_s
        self._started: float | None = None

    def __call__(self, phase: str, info: dict[str, Any]) -> None:
        if info.get("generation") != 2:
            return
        if phase == "start":
            self._started = time.perf_counter()
        elif self._started is not None:
            pause = time.perf_counter() - self._started
            self._started = None
            if pause > self.threshold_s:
                # What it had to traverse: what survived it, counted only for a long pause.
                log.warning("a full garbage collection paused every thread for %.0f ms "
                            "(%d objects freed, %d tracked objects left)", pause * 1e3,
                            info.get("collected", 0), len(gc.get_objects(generation=2)))


def watch_full_collections(threshold_s: float = LONG_PAUSE_S) -> None:
    """Log every full collection that pauses the process longer than ``threshold_s`` [s].
    Once per process; a second call changes nothing."""
    if not any(isinstance(cb, _FullCollectionWatch) for cb in gc.callbacks):
        gc.callbacks.append(_FullCollectionWatch(threshold_s))
